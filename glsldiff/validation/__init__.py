"""Validation against independent references: Mitsuba 3 Monte Carlo renders of the same scene
and the dipole. A study layer: the library never imports it.
"""
