"""The command layer: ``glsldiff`` argument parsing, calls into the library, printed tables.
No numerical logic lives here, and no library module imports it.
"""
