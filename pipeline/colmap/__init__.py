"""COLMAP models in and out: `ingest-colmap` turns a reconstruction into a site capture directory, aligned to
the map with a similarity fitted on anchor images; `export-colmap` writes a capture directory's views as a
posed COLMAP model (one rig frame per stop). Everything in the COLMAP format is read and written by pycolmap.
"""
