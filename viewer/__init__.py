"""Interactive viewer and material editor (``glsldiff.viewer``, ``glsldiff view``).

:class:`~glsldiff.viewer.window.Viewer` opens a pyglet window, renders scenes live with the
three-pass renderer in the window's own GL context, and edits the material with the GPU
operations of :mod:`glsldiff.render.editing` (section 5.4 of Wang et al. 2008).
:mod:`glsldiff.viewer.controls` holds the input state (camera orbit, light, tool) without a
window; :mod:`glsldiff.viewer.presets` the scenes Tab cycles through. pyglet is imported only
when a window opens.
"""
