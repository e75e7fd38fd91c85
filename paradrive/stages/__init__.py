"""The stages, one module each (``ingest``, ``fit``, ``render``, ``clip``, ``manifest``).

Each stage module names the typed ``Params`` of its ``stages/<name>.yaml`` (the values live only
in the YAML; ingest, fit and manifest take theirs from :mod:`paradrive.contracts.params`, which
the modules doing their work share) and ``run(ctx) -> Record``. The paths, records and contexts they share live in
:mod:`paradrive.contracts`. Nothing here imports a stage module: importing this package is cheap.
"""
