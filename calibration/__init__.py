"""Camera/projector calibration, HDR capture and measurements for inverse diffusion
(``glsldiff.calibration``; Wang et al. 2008, section 4.1).

Modules (libraries only: ``glsldiff capture <step>`` runs each step, see ``glsldiff capture
--help`` and the command layer :mod:`glsldiff.commands.capture`): ``camera`` (Zhang
intrinsics), ``projector`` (+ ``graycode``: Gray-code projector and stereo calibration),
``hdr`` (Debevec-Malik response, HDR merge), ``color`` (white balance, black level), ``plan``
(capture plan), ``rig`` (driver interface, capture loop, virtual rig), ``measure``
(measurements for ``glsldiff fit``), ``virtual`` (the whole chain on the virtual rig).
``simcam``, ``views`` and ``synth_radiometric`` simulate devices and data for tests.
"""
