"""The stages, one module each (``ingest``, ``fit``, ``render``, ``clip``, ``manifest``).

Each stage module holds the typed ``Params`` of its ``stages/<name>.yaml`` (the values live only
in the YAML) and ``run(ctx) -> Record``. :mod:`.layout` owns every path of a scene and of a build,
:mod:`.records` the typed files the stages write and read, :mod:`.base` the contexts the runner
hands a stage. Nothing here imports a stage module: importing this package is cheap.
"""
