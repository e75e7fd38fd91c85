"""The vocabulary every part of the builder shares: where a scene's and a build's files live
(:mod:`.layout`), the typed records the stages write and read (:mod:`.records`), the contexts
the runner hands a stage (:mod:`.base`), the typed parameters of the stages whose work a
module below the stages does (:mod:`.params`) and the stage definitions (:mod:`.specs`).

It imports no format, stage, pipeline module or command. The layering, lowest first, is
libraries → contracts → formats (scene, log readers, 3DGS model, manifest, adapter) → stages →
pipeline → applications → commands; ``tests/test_architecture.py`` places every folder and
top-level module in its layer (docs/architecture.md).
"""
