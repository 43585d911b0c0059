"""Training side (torch): model, losses, two-stage training, checkpoints, DDP, ONNX export."""
