"""Coarse place recognition (seed 000 section 3.1.2): IPA / RPA descriptors, whitening, two-stage retrieval."""
