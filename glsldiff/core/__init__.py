"""Core: errors, file I/O (EXR, PNG, CSV, npz; atomic writes), shared input checks and tables.

The bottom layer: it imports nothing else from glsldiff, and everything may import it.
"""
