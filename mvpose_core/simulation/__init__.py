"""Accuracy studies (the paper's Section 3.1) and station planning on synthetic observations."""
