"""prml2-edge: proprioceptive vehicle localisation from onboard CAN signals (PRML2)."""

__version__ = "0.1.0"
