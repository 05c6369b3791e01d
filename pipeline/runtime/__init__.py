"""The on-robot runtime (particle filter and its models). numpy only: never import torch here."""
