"""The stages, one module each (``ingest``, ``fit``, ``render``, ``clip``, ``manifest``).

Each stage module holds the typed ``Params`` of its ``stages/<name>.yaml`` (the values live only
in the YAML) and ``run(ctx) -> Record``. The paths, records and contexts they share live in
:mod:`paradrive.contracts`. Nothing here imports a stage module: importing this package is cheap.
"""
