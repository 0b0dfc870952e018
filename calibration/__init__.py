"""Camera/projector calibration and HDR capture (``glsldiff.calibration``).

Not implemented yet: the capture pipeline (Debevec-Malik response, Zhang calibration,
HDR merge with OpenCV) is a later issue. Importing this package does nothing.
"""
