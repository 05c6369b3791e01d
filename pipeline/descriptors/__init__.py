"""CNN layer descriptors (multilayer) and their compression to a few dimensions (compression)."""
