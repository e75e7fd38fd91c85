"""Run (scene, stage) tasks on a Ray cluster: an existing one (``address``) or a local one.

Each (scene, stage) is one Ray task that calls :func:`~paradrive.pipeline.runner.run_scene_stage`
(stages never import Ray). A scene's stages are chained: the driver submits stage k+1 of a scene
when stage k comes back, so stages run in order and scenes in parallel. Results stream back to
the driver through ``ray.wait`` and are handed to ``on_result`` (the ledger, the progress bar) as
each task finishes. Continuing a started scene goes before starting a new one, and at most
``max_in_flight`` tasks are submitted at once, so a build of thousands of scenes finishes scenes
early and keeps the driver's bookkeeping small.

Resources. A task asks for the stage's declared ``resources`` (``cpu`` -> ``num_cpus``,
``gpu`` -> ``num_gpus``, ``memory_gb`` -> ``memory``), capped to the largest node of the cluster,
so a stage never waits for a node that does not exist (a 2-CPU test cluster still runs a stage
declaring ``cpu: 4``). GPUs follow ``gpu_policy``:

- ``auto`` (default): ask for the declared GPUs; on a cluster without any GPU ask for none, with
  a warning (the stages fall back to CPU: their ``device: auto`` sees no CUDA device);
- ``require``: refuse to start when a stage declares a GPU and the cluster has none;
- ``cpu``: never ask for GPUs (every stage runs on CPU, GPUs stay free for others).

Failures. A stage that fails returns a failed result (the runner never raises for bad input);
the scene's later stages are recorded ``blocked``. A task whose worker dies (killed, out of
memory, node lost) is submitted again by the driver up to ``max_retries`` times, each time with
a new ``on_start``, so the ledger's attempts count every try (stages write atomically and are
idempotent, so a retry starts clean); after that the stage is recorded failed with Ray's reason,
and a re-run of the build finishes only what is missing.

Progress. With ``on_progress``, each task's progress (``paradrive.pipeline.progress``) is sent
by its worker to a small actor (:class:`ProgressBoard`, no CPU) at most every
:data:`RELAY_EVERY_S` seconds, its last step always; the driver takes the latest ones while it
waits for results and hands them to ``on_progress``, so the console shows the fit's iteration,
loss and PSNR of every running task across the cluster, beside the per-stage counts that
``on_start`` / ``on_result`` give. Every task also writes its progress to its scene's log.

Outputs go to the data root: a folder every node sees at the same path (a shared file system),
or an fsspec URL (``s3://…``) each worker copies a scene from and back (``paradrive.storage``).
Workers must import the same ``paradrive`` as the driver: installed on every node, or, for a
local cluster started here, the driver's checkout (put on the workers' ``PYTHONPATH``).
"""

from __future__ import annotations

import dataclasses
import os
import socket
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from paradrive.errors import ConfigError
from paradrive.pipeline.executors.base import Completion, Executor, RunOptions, SceneTask, run_stage
from paradrive.pipeline.progress import Snapshot
from paradrive.pipeline.runner import StageResult
from paradrive.contracts.specs import ResolvedConfig, Resources
from paradrive.storage import DataRoot
from paradrive.uri import parse_uri

GPU_POLICIES = ("auto", "require", "cpu")
GIB = 1024 ** 3
RELAY_EVERY_S = 1.0   # a worker sends a running task's progress to the driver at most this often


@dataclass(frozen=True)
class Capacity:
    """What the largest node of a cluster offers (a task must fit on one node)."""

    cpu: float
    gpu: float
    memory_bytes: float

    @classmethod
    def of_nodes(cls, nodes: list[dict]) -> Capacity:
        alive = [n.get("Resources", {}) for n in nodes if n.get("Alive", True)]
        return cls(cpu=max((r.get("CPU", 0.0) for r in alive), default=0.0),
                   gpu=max((r.get("GPU", 0.0) for r in alive), default=0.0),
                   memory_bytes=max((r.get("memory", 0.0) for r in alive), default=0.0))


def task_resources(stage: str, declared: Resources, capacity: Capacity,
                   gpu_policy: str = "auto") -> tuple[dict[str, Any], list[str]]:
    """Ray task options for a stage's declared resources, and the warnings the caps raise.

    Returns ``({"num_cpus", "num_gpus", "memory"}, warnings)``; raises ConfigError when
    ``gpu_policy='require'`` and the cluster has no GPU.
    """
    if gpu_policy not in GPU_POLICIES:
        raise ConfigError(f"gpu policy {gpu_policy!r}: use one of {', '.join(GPU_POLICIES)}")
    warnings: list[str] = []
    cpu = float(declared.cpu)
    if capacity.cpu and cpu > capacity.cpu:
        warnings.append(f"stage '{stage}' declares cpu: {cpu:g}; the largest node has "
                        f"{capacity.cpu:g}, asking for {capacity.cpu:g}")
        cpu = capacity.cpu
    gpu = float(declared.gpu)
    if gpu > 0:
        if gpu_policy == "cpu":
            gpu = 0.0
        elif capacity.gpu <= 0:
            if gpu_policy == "require":
                raise ConfigError(f"stage '{stage}' declares gpu: {gpu:g} but the Ray cluster has "
                                  f"no GPU; add GPU nodes or use --gpu-policy auto (run on CPU)")
            warnings.append(f"stage '{stage}' declares gpu: {gpu:g} but the cluster has no GPU; "
                            f"running it on CPU (--gpu-policy require refuses instead)")
            gpu = 0.0
        elif gpu > capacity.gpu:
            warnings.append(f"stage '{stage}' declares gpu: {gpu:g}; the largest node has "
                            f"{capacity.gpu:g}, asking for {capacity.gpu:g}")
            gpu = capacity.gpu
    memory = float(declared.memory_gb) * GIB
    if capacity.memory_bytes and memory > capacity.memory_bytes:
        warnings.append(f"stage '{stage}' declares memory_gb: {declared.memory_gb:g}; the largest "
                        f"node offers {capacity.memory_bytes / GIB:.1f} GB to tasks, asking for that")
        memory = capacity.memory_bytes
    return {"num_cpus": cpu, "num_gpus": gpu, "memory": int(memory)}, warnings


def _run_task(config: ResolvedConfig, stage: str, scene_uri: str, data_dir: DataRoot,
              options: RunOptions, board: Any = None) -> tuple[StageResult, dict]:
    """The body of one Ray task (runs on a worker; ``options`` without the driver's callbacks);
    its progress goes to ``board``."""
    started = time.time()
    relay = _Relay(board) if board is not None else None
    result = run_stage(config, stage, scene_uri, data_dir, dataclasses.replace(options, on_progress=relay))
    return result, {"host": socket.gethostname(), "pid": os.getpid(), "started_at": started}


class ProgressBoard:
    """A Ray actor holding the latest progress :class:`~paradrive.pipeline.progress.Snapshot`
    of every running task; the driver takes them while it waits for results."""

    def __init__(self) -> None:
        self.latest: dict[tuple[str, str], Snapshot] = {}

    def put(self, snap: Snapshot) -> None:
        self.latest[(snap.scene_id, snap.stage)] = snap

    def take(self) -> list[Snapshot]:
        snaps, self.latest = list(self.latest.values()), {}
        return snaps


class _Relay:
    """A task's progress sink on a worker: to the board at most every ``every_s`` seconds, the
    stage's last step always (and waited for, so the driver has it before the result)."""

    def __init__(self, board: Any, every_s: float = RELAY_EVERY_S):
        self.board, self.every_s, self.sent = board, every_s, float("-inf")

    def __call__(self, snap: Snapshot) -> None:
        now = time.monotonic()
        if snap.done >= snap.total:
            import ray

            ray.get(self.board.put.remote(snap))
        elif now - self.sent >= self.every_s:
            self.board.put.remote(snap)
        else:
            return
        self.sent = now


def _checkout_root() -> str:
    import paradrive

    return str(Path(paradrive.__file__).resolve().parents[1])


class RayExecutor(Executor):
    name = "ray"

    def __init__(self, address: str | None = None, *, gpu_policy: str = "auto",
                 max_in_flight: int | None = None, max_retries: int = 2,
                 num_cpus: int | None = None, num_gpus: int | None = None,
                 init_options: dict | None = None):
        if gpu_policy not in GPU_POLICIES:
            raise ConfigError(f"--gpu-policy {gpu_policy!r}: use one of {', '.join(GPU_POLICIES)}")
        super().__init__()
        self.address = address
        self.gpu_policy = gpu_policy
        self.max_in_flight = max_in_flight
        self.max_retries = max_retries
        self.num_cpus = num_cpus
        self.num_gpus = num_gpus
        self.init_options = dict(init_options or {})
        self.warnings: list[str] = []
        self.placements: dict[tuple[str, str], dict] = {}  # (scene_id, stage) -> host, pid, start

    # -- cluster ------------------------------------------------------------------------------

    def _connect(self):
        """Connect to (or start) Ray; returns (ray, whether this call started it)."""
        try:
            import ray
        except ModuleNotFoundError as exc:
            raise ConfigError("the ray executor needs Ray: pip install 'ray[default]'") from exc
        if ray.is_initialized():
            return ray, False
        options: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False,
                                   **self.init_options}
        if self.address:
            options["address"] = self.address
        else:
            # A local cluster: workers import this checkout even when it is not installed.
            root = _checkout_root()
            path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH", "")) if p)
            env = {"PYTHONPATH": path}
            if os.environ.get("PARADRIVE_STAGES"):
                env["PARADRIVE_STAGES"] = os.environ["PARADRIVE_STAGES"]
            options.setdefault("runtime_env", {"env_vars": env})
            if self.num_cpus is not None:
                options["num_cpus"] = self.num_cpus
            if self.num_gpus is not None:
                options["num_gpus"] = self.num_gpus
        try:
            ray.init(**options)
        except ConnectionError as exc:
            raise ConfigError(f"cannot reach the Ray cluster at {self.address}: {exc}; start it "
                              f"with 'ray start --head' or leave out --address for a local one") from exc
        return ray, True

    def plan(self, config: ResolvedConfig, stages: list[str], capacity: Capacity) -> dict[str, dict]:
        """Ray options per stage (see the module doc for the policy); warnings go to the log."""
        registry = config.registry()
        options: dict[str, dict] = {}
        for stage in stages:
            opts, warnings = task_resources(stage, registry.specs[stage].resources, capacity,
                                            self.gpu_policy)
            options[stage] = opts
            for w in warnings:
                if w not in self.warnings:
                    self.warnings.append(w)
                    self.log.warning(w)
        return options

    # -- running ------------------------------------------------------------------------------

    def run_tasks(self, config: ResolvedConfig, tasks: list[SceneTask], data_dir: DataRoot,
                  options: RunOptions, done: Completion) -> None:
        ray, started_here = self._connect()
        try:
            self._run(ray, config, tasks, data_dir, options, done)
        finally:
            if started_here:
                ray.shutdown()

    def run_build_stage(self, config: ResolvedConfig, stage: str,
                        call: Callable[[], StageResult]) -> StageResult:
        """A build stage that declares a GPU (``encode``) runs as one Ray task with its stage's
        resources, so a driver without a GPU hands it to a node with one; the others (the
        manifest) stay in the driver, which holds their scene locks. The task reads and writes
        the build folder and the data root at the driver's paths: on a cluster both are on
        storage every node mounts (or the data root is a URL). ``summary["worker"]`` says where
        it ran."""
        if config.registry().specs[stage].resources.gpu <= 0:
            return call()
        ray, started_here = self._connect()
        try:
            options = self.plan(config, [stage], Capacity.of_nodes(ray.nodes()))[stage]
            ref = ray.remote(_run_build_task).options(**options, max_retries=0, retry_exceptions=False,
                                                      name=f"{stage}:build").remote(call)
            result, where = ray.get(ref)
        finally:
            if started_here:
                ray.shutdown()
        result.summary["worker"] = {**where, "num_gpus": options["num_gpus"]}
        return result

    def _run(self, ray, config: ResolvedConfig, tasks: list[SceneTask], data_dir: DataRoot,
             options: RunOptions, done: Completion) -> None:
        capacity = Capacity.of_nodes(ray.nodes())
        all_stages = sorted({s for t in tasks for s in t.stages})
        total = ray.cluster_resources()  # the whole cluster: enough queued to keep every node busy
        window = self.max_in_flight or max(2, int(2 * (total.get("CPU", 0) + total.get("GPU", 0))))
        board = ray.remote(num_cpus=0)(ProgressBoard).remote() if options.on_progress else None
        dispatch = _Dispatch(self, ray, self.plan(config, all_stages, capacity), ray.put(config),
                             (data_dir, options.for_worker(), board),
                             options, done)
        queue = deque(tasks)
        try:
            while queue or dispatch.in_flight:
                while queue and len(dispatch.in_flight) < window:
                    dispatch.submit(queue.popleft(), 0)
                ready, _ = ray.wait(list(dispatch.in_flight), num_returns=1,
                                    timeout=RELAY_EVERY_S if board else None)
                if board is not None and options.on_progress is not None:
                    for snap in ray.get(board.take.remote()):
                        options.on_progress(snap)
                for ref in ready:
                    dispatch.collect(ref)
        except BaseException:
            # The driver stops (Ctrl-C, an error in a callback): withdraw what it submitted, so
            # a shared cluster does not go on working for nobody. Atomic writes keep outputs whole.
            dispatch.cancel_all()
            raise


def _run_build_task(call: Callable[[], StageResult]) -> tuple[StageResult, dict]:
    """The body of a build stage's Ray task."""
    started = time.time()
    return call(), {"host": socket.gethostname(), "pid": os.getpid(), "started_at": started}


def _scene_id(scene_uri: str) -> str:
    try:
        return parse_uri(scene_uri).scene_id
    except ConfigError:
        return scene_uri


def lost_result(scene_uri: str, stage: str, exc: BaseException, retries: int) -> StageResult:
    """The failed result of a task Ray could not complete (its worker died every time)."""
    text = str(exc).strip().splitlines()
    reason = text[0] if text else ""
    sid = _scene_id(scene_uri)
    return StageResult(sid, stage, "failed",
                       error=f"scene {sid}: {stage} lost on the Ray cluster after "
                             f"{retries + 1} attempt(s): {type(exc).__name__}: {reason}; "
                             f"re-run the build to finish it (outputs are written atomically)")


class _Dispatch:
    """The tasks a Ray run has in flight: submit a scene's next stage, collect a finished one
    (retrying a lost task, blocking the stages after a failed one)."""

    def __init__(self, executor: RayExecutor, ray, task_options: dict, config_ref, args: tuple,
                 options: RunOptions, done: Completion):
        self.executor, self.ray, self.task_options, self.config_ref = executor, ray, task_options, config_ref
        self.args, self.on_start, self.done = args, options.on_start, done
        self.remote = ray.remote(_run_task)
        self.in_flight: dict[Any, tuple[SceneTask, int, int]] = {}  # ref -> (task, stage index, try)

    def submit(self, task: SceneTask, index: int, attempt: int = 1) -> None:
        stage = task.stages[index]
        if self.on_start:
            self.on_start(task.scene_uri, stage)
        # Ray does not retry by itself: the driver does, so every try is seen and counted.
        ref = self.remote.options(**self.task_options[stage], max_retries=0, retry_exceptions=False,
                                  name=f"{stage}:{_scene_id(task.scene_uri)}").remote(
            self.config_ref, stage, task.scene_uri, *self.args)
        self.in_flight[ref] = (task, index, attempt)

    def collect(self, ref) -> None:
        task, index, attempt = self.in_flight.pop(ref)
        stage = task.stages[index]
        retries = self.executor.max_retries
        try:
            result, where = self.ray.get(ref)
            self.executor.placements[(result.scene_id, stage)] = where
        except Exception as exc:  # the task was lost: worker died, node gone, ...
            if attempt <= retries:
                self.executor.log.warning("%s of %s lost (%s: %s); try %d of %d", stage,
                                          _scene_id(task.scene_uri), type(exc).__name__,
                                          (str(exc).strip().splitlines() or [""])[0], attempt + 1,
                                          retries + 1)
                self.submit(task, index, attempt + 1)
                return
            result = lost_result(task.scene_uri, stage, exc, retries)
        if self.done.stage_done(task, index, result):
            self.submit(task, index + 1)  # a started scene goes before a new one

    def cancel_all(self) -> None:
        for ref in self.in_flight:
            try:
                self.ray.cancel(ref)
            except Exception:
                pass
