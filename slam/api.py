"""High-level entry points used by the CLI and by scripts: a run folder from a sequence folder,
and the resumption of an interrupted run."""

from __future__ import annotations

import logging
import signal
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from slam.config import SlamConfig, load_config
from slam.data.base import Sequence
from slam.data.loader import open_sequence
from slam.errors import ConfigError, DatasetError, RunFolderError
from slam.pipeline import DeferSignals, FrameCallback, ProgressCallback, RunResult, run
from slam.run_folder import (
    CHECKPOINT_DIR,
    CONFIG_FILE,
    METRICS_FILE,
    RunFolder,
    clear_run_dir,
    make_run_dir,
    prepare_run_dir,
    remove_work_dirs,
    save_run,
    write_config,
)
from slam.run_folder.checkpoint import STATE_FILE, has_checkpoint
from slam.run_folder.lock import RunLock
from slam.saved_map import Map

log = logging.getLogger(__name__)


def run_sequence(
    sequence: str | Path | None,
    out_dir: str | Path,
    config_path: str | Path | None = None,
    config: SlamConfig | None = None,
    max_frames: int | None = None,
    progress: ProgressCallback | None = None,
    checkpoint_every: int | None = None,
    overwrite: bool = False,
    on_frame: FrameCallback | None = None,
    rerun: str | Path | None = None,
    workers: int = 1,
    ray_address: str | None = None,
    executor: str = "auto",
    worker_threads: int | None = None,
    map_dir: str | Path | None = None,
    first_frame: int | None = None,
    extend: bool = False,
) -> tuple[RunResult, Path]:
    """Open a sequence folder (``None``: the built-in synthetic demo), run SLAM, save the run
    folder. Config: ``config`` if given, else defaults overridden by the YAML at ``config_path``.
    ``rerun``: also record the run for the rerun viewer into this ``.rrd`` file
    (:class:`slam.tools.viewer.RerunRecorder`; needs the ``viz`` extra).

    Before the first frame: the config and the sequence are checked, and ``out_dir`` must be
    writable and must not hold another run unless ``overwrite`` (which deletes its outputs).
    ``config.yaml`` is written at once, with the calibration the sequence was read with (all of
    its fields in ``dataset.calibration``, so the file reproduces the run on a renamed copy of
    the folder), ``metrics.json`` last; the state goes to ``out_dir/checkpoint/``
    every ``checkpoint_every`` frames (None: automatically, at most 2% of the run time; 0:
    never; always on SIGINT/SIGTERM) so :func:`resume_run` can continue after a kill.

    ``workers`` > 1: the sequence is cut into that many overlapping chunks, tracked at once in
    worker processes (Ray tasks: a local Ray instance, or the cluster at ``ray_address``; local
    processes where Ray is not installed; ``executor`` forces one; ``worker_threads``: kernel
    threads per worker, default the cores over the workers) and joined
    (:mod:`slam.chunked`); a finished chunk is kept, so :func:`resume_run` continues after a
    kill without redoing it. ``progress`` then counts the frames the workers have stepped
    (``status`` None); the per-frame hooks (``on_frame``, ``rerun``) see no frames: the frames
    are tracked in other processes.

    ``map_dir``: a finished run folder whose map (``map/``) the sequence is localised in
    instead of mapped (:mod:`slam.localisation`; read only, so several runs may share it;
    a camera other than the map's is refused before the first frame). ``first_frame``: start
    at this frame of the sequence (``dataset.first_frame``: a recording split in two).
    ``extend`` (with ``map_dir``): map the sequence, then join it to that map
    (:func:`slam.merge.extend_map`): the run folder gets the merged mesh and map, the new
    frames' poses in the map's frame (the old folder is left as it was); a recording that never
    meets the map stays in its own frame, reported as not joined.
    """
    cfg = config if config is not None else load_config(config_path)
    if first_frame is not None:
        cfg.dataset.first_frame = first_frame
    saved = None
    if extend and map_dir is None:
        raise ConfigError("extend needs the map to extend: give map_dir (--map RUN_DIR)")
    if map_dir is not None:
        if workers > 1:
            raise ConfigError("--map localises on one worker: leave out --workers")
        saved = Map.load(map_dir)
    if max_frames is not None:
        if max_frames < 1:
            raise ConfigError(f"max_frames must be >= 1 (or None for all), got {max_frames}")
        cfg.dataset.max_frames = max_frames
    cfg.validate()
    created = not Path(out_dir).exists()
    out = make_run_dir(out_dir)  # what it holds is checked once the folder is locked
    with _claimed(out, created):
        prepare_run_dir(out, overwrite)
        if sequence is None:
            from slam.demo import demo_sequence_path

            sequence = demo_sequence_path()
        cfg.dataset.path = str(Path(sequence).resolve())
        seq: Sequence = open_sequence(sequence, cfg.dataset.layout, cfg.dataset.calibration)
        _warn_overridden_calibration(seq, cfg)
        # the calibration the run uses, whatever chose it (calibration.yaml, TUM defaults by
        # folder name, overrides): config.yaml then reproduces it on a renamed copy
        cfg.dataset.calibration = dict(seq.calibration.to_dict())
        if saved is not None:
            c = seq.calibration
            saved.check_camera(c.K, (c.width, c.height), f"{seq.path}")
        recorder = _recorder(rerun, seq.name)
        write_config(out, cfg)
        if workers > 1:
            from slam.chunked.runner import run_chunked

            def run_fn(hook: FrameCallback | None) -> RunResult:
                return run_chunked(seq, cfg, out, workers, executor=executor,
                                   ray_address=ray_address, threads=worker_threads,
                                   progress=progress)  # fmt: skip
        else:

            def run_fn(hook: FrameCallback | None) -> RunResult:
                result = run(seq, cfg, progress=progress, run_dir=out,
                             checkpoint_every=checkpoint_every, on_frame=hook,
                             map=None if extend else saved)  # fmt: skip
                if extend:
                    assert saved is not None
                    result = _extended(result, saved, seq, cfg)
                return result

        result = _recorded(recorder, run_fn, on_frame, out)
    return result, out


def _extended(result: RunResult, saved: Map, seq: Sequence, cfg: SlamConfig) -> RunResult:
    """The new run joined to the saved map (:func:`slam.merge.extend_map`), with the join's
    report and, when joined and with ground truth, the error in the map's frame."""
    from slam.merge import extend_map
    from slam.pipeline import evaluate_in_map_frame

    result, report = extend_map(saved, result, cfg)
    m = result.metrics
    m.extended_map = str(saved.source)
    m.map_extension = report.as_json()
    if report.joined and len(result.trajectory):
        m.update(evaluate_in_map_frame(seq, result.trajectory, str(saved.source)))
    return result


def _warn_overridden_calibration(seq: Sequence, cfg: SlamConfig) -> None:
    """Warn when the config's ``dataset.calibration`` changes the calibration the sequence
    folder gives itself (``calibration.yaml``, TUM defaults by folder name): e.g. a run's saved
    ``config.yaml`` reused on another sequence brings that run's intrinsics along."""
    if not any(v is not None for v in cfg.dataset.calibration.values()):
        return
    try:
        own = open_sequence(seq.path, cfg.dataset.layout, None).calibration
    except DatasetError:  # no calibration of its own: the config's is the one
        return
    ours, theirs = seq.calibration.to_dict(), own.to_dict()
    source = (
        "its calibration.yaml"
        if (Path(seq.path) / "calibration.yaml").is_file()
        else "the TUM defaults for its folder name"
    )
    changed = [
        f"{k} {_number(ours.get(k))} (the folder's: {_number(theirs.get(k))})"
        for k in [*ours, *(k for k in theirs if k not in ours)]
        if ours.get(k) != theirs.get(k)
    ]
    if changed:
        log.warning(
            "%s: the config's dataset.calibration replaces what the folder gives (%s): %s; "
            "remove dataset.calibration from the config to use the folder's",
            seq.path, source, ", ".join(changed),
        )  # fmt: skip


def _number(value: float | None) -> str:
    return "none" if value is None else f"{value:g}"


@contextmanager
def _claimed(out: Path, created: bool) -> Iterator[None]:
    """Hold the run folder's lock while the run writes it. A run that fails before its first
    checkpoint leaves nothing behind (no config.yaml, spilled submaps or half-written results, no
    folder it created), so the corrected run needs no --overwrite; one with a checkpoint stays
    resumable."""
    try:
        with RunLock(out):
            try:
                yield
            except BaseException:
                if not (has_checkpoint(out) or _chunked(out)):
                    clear_run_dir(out)  # nothing of it can be resumed: leave the folder free
                raise
    finally:
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()


def _chunked(run_dir: Path) -> bool:
    from slam.chunked.runner import is_chunked

    return is_chunked(run_dir)


def _recorder(path: str | Path | None, name: str) -> Any:
    if path is None:
        return None
    from slam.tools.viewer import RerunRecorder

    return RerunRecorder(path, name=name)


def _recorded(
    recorder: Any,
    run_fn: Callable[[FrameCallback | None], RunResult],
    on_frame: FrameCallback | None,
    out: Path,
) -> RunResult:
    """Run with the recorder's hook chained after ``on_frame``; save the run folder, then close
    the recording (an unfinished one is deleted)."""
    hook = on_frame
    if recorder is not None:

        def hook(frame, frame_result) -> None:  # type: ignore[no-redef]
            if on_frame is not None:
                on_frame(frame, frame_result)
            recorder.on_frame(frame, frame_result)

    try:
        result = run_fn(hook)
        with DeferSignals() as deferred:  # a finished run's results are written whole
            save_run(result, out, overwrite=True)  # the folder was prepared for this run
            remove_work_dirs(out)
    except BaseException:
        if recorder is not None:
            recorder.abort()
        raise
    if deferred.requested is not None:
        log.warning("%s: %s holds the complete run", signal.Signals(deferred.requested).name, out)
    if recorder is not None:
        recorder.finish(result)
    return result


def resume_run(
    run_dir: str | Path,
    progress: ProgressCallback | None = None,
    checkpoint_every: int | None = None,
    on_frame: FrameCallback | None = None,
    rerun: str | Path | None = None,
) -> tuple[RunResult, Path]:
    """Continue an interrupted run from its last checkpoint, with the config it was started
    with (``run_dir/config.yaml``), and write the same outputs as an uninterrupted run.
    ``checkpoint_every``: default the interrupted run's. ``rerun``: record the resumed frames
    and the result into this ``.rrd`` file (``slam view`` records the whole run afterwards)."""
    folder = RunFolder(run_dir)
    run_dir = folder.path
    if not run_dir.is_dir():
        raise RunFolderError(f"{run_dir}: run folder not found")
    with RunLock(run_dir):
        return _resume(folder, progress, checkpoint_every, on_frame, rerun)


def _resume_chunked(
    folder: RunFolder, progress: ProgressCallback | None, rerun: str | Path | None
) -> tuple[RunResult, Path]:
    """Continue a parallel run: its chunks that finished are kept, the others run again."""
    from slam.chunked.runner import read_plan, run_chunked

    run_dir = folder.path
    cfg = load_config(folder.file(CONFIG_FILE))
    seq = open_sequence(cfg.dataset.path, cfg.dataset.layout, cfg.dataset.calibration)
    workers = int(read_plan(run_dir)["workers"])
    result = _recorded(
        _recorder(rerun, seq.name),
        lambda hook: run_chunked(seq, cfg, run_dir, workers, resume=True, progress=progress),
        None,
        run_dir,
    )
    return result, run_dir


def _resume(
    folder: RunFolder,
    progress: ProgressCallback | None,
    checkpoint_every: int | None,
    on_frame: FrameCallback | None,
    rerun: str | Path | None,
) -> tuple[RunResult, Path]:
    run_dir = folder.path
    if folder.complete:
        raise RunFolderError(f"{run_dir}: the run is complete ({METRICS_FILE}); nothing to resume")
    if _chunked(run_dir):
        return _resume_chunked(folder, progress, rerun)
    if not has_checkpoint(run_dir):
        raise RunFolderError(
            f"{run_dir}: no checkpoint to resume from ({CHECKPOINT_DIR}/{STATE_FILE}); the run "
            "was stopped before its first checkpoint or ran with --checkpoint-every 0: start "
            "it again with --overwrite"
        )
    cfg = load_config(folder.file(CONFIG_FILE))
    if not cfg.dataset.path:
        raise RunFolderError(f"{folder.file(CONFIG_FILE)}: dataset.path is missing")
    seq = open_sequence(cfg.dataset.path, cfg.dataset.layout, cfg.dataset.calibration)
    recorder = _recorder(rerun, seq.name)
    result = _recorded(
        recorder,
        lambda hook: run(
            seq,
            cfg,
            progress=progress,
            run_dir=run_dir,
            checkpoint_every=checkpoint_every,
            resume=True,
            on_frame=hook,
        ),
        on_frame,
        run_dir,
    )
    return result, run_dir
