"""CAN-side helpers shared by the encoder and the runtime (no torch)."""
