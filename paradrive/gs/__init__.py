"""3D Gaussian Splatting: model, initialisation, densification, PLY I/O, rasterizer and the fit stage.

Render a checkpoint with :func:`paradrive.gs.fit.render_checkpoint`; read one with
:func:`paradrive.gs.ply.load_ply`.
"""
