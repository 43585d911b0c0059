"""Running the edge runtime as a service: systemd notify/watchdog, ``prml2 doctor`` checks."""
