"""Test tooling shipped with the package (not used by the runtime): fault injection for CAN logs."""
