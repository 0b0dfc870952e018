"""Interactive viewer and material editor (``glsldiff.viewer``).

Not implemented yet: the three-pass renderer and the editor are later issues.
Importing this package does nothing.
"""
