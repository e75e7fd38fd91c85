"""The vocabulary every part of the builder shares: where a scene's and a build's files live
(:mod:`.layout`), the typed records the stages write and read (:mod:`.records`), the contexts
the runner hands a stage (:mod:`.base`) and the typed parameters of the stages whose work a
module below the stages does (:mod:`.params`).

It imports no stage, no pipeline module and no CLI. The layering, lowest first, is libraries →
contracts → formats (scene, log readers, 3DGS model, manifest, adapter) → stages → pipeline →
cli; ``tests/test_architecture.py`` lists every module's layer.
"""
