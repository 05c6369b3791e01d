"""Seed 001: an area prior from pretrained multi-layer CNN features (no training), and its evaluation."""
