"""Running the edge runtime as a service: systemd notify/watchdog, execution-provider choice."""
