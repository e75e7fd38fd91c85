"""The vocabulary every part of the builder shares: where a scene's and a build's files live
(:mod:`.layout`), the typed records the stages write and read (:mod:`.records`), and the contexts
the runner hands a stage (:mod:`.base`).

Libraries may import this package; it imports no stage, no pipeline module and no CLI. The
layering is libraries → contracts → stages → pipeline → cli (``tests/test_architecture.py``).
"""
