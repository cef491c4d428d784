"""The authors' released PyTorch checkpoints: reading and key mapping."""
