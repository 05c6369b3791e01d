"""Keeping a site database current after the building changes: `siteloc update` (see docs/update.md)."""
