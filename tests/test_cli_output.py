"""What the command line prints and records (issue 19, items 10, 11, 13, 14): output to a pipe
is never wrapped, `--help` shows install commands and flags as they are typed, `--version`, the
software and the calibration a run used are in its folder, `slam view --open` without a
display says so."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

import slam
from slam.cli import app
from slam.run_folder import provenance

runner = CliRunner()
ROOT = Path(__file__).resolve().parents[1]


def flat(text: str) -> str:
    return " ".join(text.split())


def deep(tmp_path: Path) -> Path:
    """A folder whose path is well over 80 characters (as under a long $TMPDIR)."""
    path = tmp_path / ("d" * 60) / ("e" * 60)
    path.mkdir(parents=True, exist_ok=True)
    return path


def slam_cli(*args: str | Path, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """`slam ARGS` in a subprocess with stdout and stderr piped (not a terminal)."""
    env = {**os.environ, "COLUMNS": "80"}  # the width a terminal would have; a pipe ignores it
    env.pop("FORCE_COLOR", None)
    env.pop("TTY_COMPATIBLE", None)
    return subprocess.run(
        [sys.executable, "-m", "slam", *map(str, args)],
        capture_output=True, text=True, env=env, cwd=cwd, timeout=600, check=False,
    )  # fmt: skip


# --- item 10: output to a pipe or a file is not wrapped


def test_piped_error_keeps_a_long_path_on_one_line(tmp_path):
    missing = deep(tmp_path) / "no-such-run-folder-with-a-long-name"
    res = slam_cli("report", missing)
    assert res.returncode == 2, res.stderr
    assert f"error: {missing}: run folder not found" in res.stderr.splitlines()
    res = slam_cli("run", missing, "--out", deep(tmp_path) / "out")
    assert res.returncode == 2
    assert f"error: {missing}: sequence folder not found" in res.stderr.splitlines()


@pytest.mark.slow
def test_piped_run_prints_whole_lines(tmp_path):
    """`slam run` to a pipe: the files written, the `rerun ...` command and the final progress
    line each stay on one line, nothing padded to a width."""
    from slam.synthetic import SynthConfig, generate_sequence

    seq = generate_sequence(
        tmp_path / "seq", SynthConfig.half_resolution(frames=300, render_frames=3)
    )
    out = deep(tmp_path) / "run-with-a-long-name"
    args: list[str | Path] = ["run", seq, "--out", out, "--max-frames", "3"]
    rrd = None
    try:
        import rerun  # noqa: F401

        rrd = out.parent / "recording-with-a-long-name.rrd"
        args += ["--rerun", rrd]
    except ImportError:
        pass
    res = slam_cli(*args)
    assert res.returncode == 0, res.stderr
    lines = res.stderr.splitlines()
    assert any(line.startswith(f"wrote {out}: ") and "metrics.json" in line for line in lines)
    if rrd is not None:
        assert f"wrote {rrd} (open it with `rerun {rrd}`)" in lines
    bar = [line for line in lines if line.startswith("tracking")]
    assert bar and "3/3" in bar[-1] and "finishing" in bar[-1], lines
    assert not [line for line in lines if line != line.rstrip()]  # not padded to a width
    assert "3 frames" in res.stdout


def test_long_tmpdir_paths_in_cli_runner_output(tmp_path):
    """In-process (as the tests invoke the CLI) the same holds: a long path is one line."""
    missing = deep(tmp_path) / "nope"
    res = runner.invoke(app, ["report", str(missing)])
    assert res.exit_code == 2
    assert f"error: {missing}: run folder not found" in res.output.splitlines()


# --- item 14: --help


def test_help_shows_install_commands_and_flags_as_typed():
    res = runner.invoke(app, ["run", "--help"])
    assert res.exit_code == 0, res.output
    text = flat(res.output)
    assert "pip install -e '.[viz]'" in text  # `[viz]` was taken for rich markup and dropped
    assert "<bool>" not in text and "<int>" not in text
    assert re.search(r"^\s*--overwrite\s+Replace", res.output, re.M), res.output
    assert re.search(r"^\s*-v, --verbose\s+Log every event", res.output, re.M), res.output
    assert re.search(r"^\s*--help\s+Show this message", res.output, re.M), res.output
    assert "<path>" in text  # options that take a value still name it
    res = runner.invoke(app, ["bench", "--help"])
    assert "[runs/bench/SUITE_NAME]" in flat(res.output)
    res = runner.invoke(app, ["--help"])
    assert res.exit_code == 0 and "<bool>" not in res.output
    for name in ("run", "view", "synth", "eval", "report", "bench"):  # one line each, whole
        line = next(x for x in res.output.splitlines() if x.strip().startswith(name + " "))
        assert not line.rstrip().endswith("..."), line


def test_readme_install_commands_work_from_a_checkout():
    """The package is not on PyPI: the README installs the extras from the checkout."""
    readme = (ROOT / "README.md").read_text()
    assert "pip install 'rgbd-slam[viz]'" not in readme
    assert "pip install -e '.[viz]'" in readme


# --- item 11: --version, the software and the calibration in the run folder


def test_version():
    res = runner.invoke(app, ["--version"])
    assert res.exit_code == 0, res.output
    assert res.output.split()[:2] == ["rgbd-slam", slam.__version__]
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert re.search(r'^version = "([^"]+)"$', pyproject, re.M)[1] == slam.__version__
    res = slam_cli("--version")
    assert res.returncode == 0 and res.stdout.startswith(f"rgbd-slam {slam.__version__}")


def test_git_commit_is_none_outside_a_checkout_never_an_error(monkeypatch):
    provenance.git_state.cache_clear()
    try:
        commit, _ = provenance.git_state()
        if provenance.checkout_root() is not None and shutil.which("git"):
            assert commit is not None and re.fullmatch(r"[0-9a-f]{40}", commit)
        provenance.git_state.cache_clear()
        monkeypatch.setattr(provenance, "checkout_root", lambda: None)  # an installed package
        assert provenance.software() == {
            "slam_version": slam.__version__,
            "git_commit": None,
            "git_dirty": None,
        }
        assert provenance.software_line() == f"rgbd-slam {slam.__version__}"
        provenance.git_state.cache_clear()
        monkeypatch.setattr(provenance, "checkout_root", lambda: ROOT)
        monkeypatch.setenv("PATH", "")  # no git program
        assert provenance.git_state() == (None, None)
    finally:
        provenance.git_state.cache_clear()


def _tum_fr1_folder(path: Path) -> Path:
    """A small TUM-like folder at 640x480 with no calibration.yaml: its name (freiburg1) picks
    TUM's fr1 intrinsics and undistortion."""
    from slam.synthetic import SynthConfig, generate_sequence

    seq = generate_sequence(path, SynthConfig(frames=300, render_frames=3, noise=False))
    (seq / "calibration.yaml").unlink()
    return seq


@pytest.mark.slow
def test_run_folder_records_software_and_the_calibration_used(tmp_path):
    from slam.api import run_sequence
    from slam.config import load_config
    from slam.data.calibration import TUM_DEFAULTS
    from slam.data.loader import open_sequence
    from slam.errors import CalibrationError

    seq = _tum_fr1_folder(tmp_path / "rgbd_dataset_freiburg1_tiny")
    fr1 = TUM_DEFAULTS["freiburg1"]
    _, run_dir = run_sequence(seq, tmp_path / "run", max_frames=2)

    text = (run_dir / "config.yaml").read_text()
    assert text.startswith(f"# written by rgbd-slam {slam.__version__}")
    cfg = load_config(run_dir / "config.yaml")  # the header is a comment: it loads as before
    assert cfg.dataset.calibration == fr1.to_dict()  # not `{}`: intrinsics and distortion
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["slam_version"] == slam.__version__
    assert metrics["git_commit"] is None or re.fullmatch(r"[0-9a-f]{40}", metrics["git_commit"])
    assert metrics["git_dirty"] in (None, True, False)
    assert (metrics["git_commit"] is None) == (metrics["git_dirty"] is None)

    # a renamed copy: its name no longer says freiburg1, so it has no calibration of its own...
    copy = Path(shutil.copytree(seq, tmp_path / "my_recording"))
    with pytest.raises(CalibrationError):
        open_sequence(copy)
    # ... and the saved config gives it the same one: same K, same undistortion
    reopened = open_sequence(copy, cfg.dataset.layout, cfg.dataset.calibration)
    assert reopened.calibration == fr1
    assert (reopened[0].K == open_sequence(seq)[0].K).all()
    res = runner.invoke(
        app, ["run", str(copy), "--out", str(tmp_path / "run2"), "-c", str(run_dir / "config.yaml")]
    )
    assert res.exit_code == 0, res.output
    again = load_config(tmp_path / "run2" / "config.yaml")
    assert again.dataset.calibration == fr1.to_dict()
    assert again.dataset.path == str(copy.resolve())
    assert "dataset.calibration replaces" not in res.output


def test_config_calibration_that_changes_the_folders_own_is_warned(tmp_path, caplog):
    """A saved config.yaml reused on another sequence brings its calibration along: said."""
    from slam.api import _warn_overridden_calibration
    from slam.config import config_from_dict
    from slam.data.loader import open_sequence
    from slam.synthetic import SynthConfig, generate_sequence

    seq = generate_sequence(
        tmp_path / "seq", SynthConfig.half_resolution(frames=300, render_frames=1)
    )
    own = open_sequence(seq).calibration
    same = config_from_dict({"dataset": {"calibration": own.to_dict()}})
    _warn_overridden_calibration(open_sequence(seq, "auto", same.dataset.calibration), same)
    assert not caplog.records
    other = config_from_dict({"dataset": {"calibration": {**own.to_dict(), "fx": 300.0}}})
    _warn_overridden_calibration(open_sequence(seq, "auto", other.dataset.calibration), other)
    assert "fx 300 (the folder's: 262.5)" in caplog.text
    assert "replaces what the folder gives (its calibration.yaml)" in caplog.text


# --- item 13: slam view --open without a display


def test_view_open_without_display_fails_and_keeps_the_recording(tmp_path, monkeypatch):
    import slam.tools.viewer as viewer

    run_dir = deep(tmp_path)

    def record(run_dir, out=None, image_scale=4):  # the recording itself is tested elsewhere
        path = Path(out) if out is not None else Path(run_dir) / "recording.rrd"
        path.write_bytes(b"rrd")
        return path

    def no_viewer(*args, **kwargs):
        raise AssertionError("no viewer may be started without a display")

    monkeypatch.setattr(viewer, "record_run_folder", record)
    monkeypatch.setattr(viewer.subprocess, "Popen", no_viewer)
    monkeypatch.setattr(viewer.sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    res = runner.invoke(app, ["view", str(run_dir), "--open"])
    rrd = run_dir / "recording.rrd"
    assert res.exit_code != 0
    assert rrd.is_file()  # kept
    errors = [line for line in res.output.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, res.output  # one line
    assert "no display" in errors[0] and f"kept in {rrd}" in errors[0]
    assert "`rerun recording.rrd`" in errors[0]

    monkeypatch.setenv("WAYLAND_DISPLAY", "wayland-0")
    assert viewer.no_display_reason() is None
    assert viewer.no_display_reason({"DISPLAY": ":0"}) is None
    assert "DISPLAY" in viewer.no_display_reason({})
    monkeypatch.setattr(viewer.sys, "platform", "darwin")
    assert viewer.no_display_reason({}) is None


def test_the_progress_bar_of_a_parallel_run_says_what_the_workers_do():
    """With --workers N the frames come from worker processes: no tracking status, no
    'skipped' for them; at the end the bar says the chunks are being joined."""
    from slam.cli import _RunProgress

    for parallel, during, end in [
        (True, "workers tracking their chunks", "joining the chunks, finishing"),
        (False, "skipped (unreadable)", "finishing"),
    ]:
        bar = _RunProgress(quiet=False, parallel=parallel)
        try:
            bar.on_frame(5, 10, None)
            assert during in bar.bar.tasks[0].fields["state"]
            bar.on_frame(10, 10, None)
            assert bar.bar.tasks[0].fields["state"].startswith(end)
        finally:
            bar.stop()


def test_a_run_to_a_pipe_prints_a_plain_progress_line_every_few_seconds(capsys):
    """Not on a terminal (a pipe, a file: rich draws no bar there) the run's progress is a
    plain line every few seconds, and one when the frames are done; nothing with --quiet."""
    from slam.cli import _RunProgress

    progress = _RunProgress(quiet=False)
    assert progress.plain  # the tests' stderr is not a terminal
    progress.PLAIN_EVERY_S = 0.0
    for done in range(1, 4):
        progress.on_frame(done, 3, None)
    progress.stop()
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 3 and lines[0].startswith("tracking 1/3 frames, "), lines
    assert lines[-1].startswith("tracking 3/3 frames") and "finishing" in lines[-1]
    assert "\x1b" not in "".join(lines)
    quiet = _RunProgress(quiet=True)
    quiet.on_frame(1, 3, None)
    assert capsys.readouterr().err == ""


def test_a_library_message_reaches_a_file_without_colour_codes(capsys):
    """Open3D's error text carries a terminal's colour codes; `error: ...` does not."""
    import typer

    from slam import cli_app
    from slam.errors import SlamError

    with pytest.raises(typer.Exit):
        cli_app._fail(SlamError("\x1b[1;31m[Open3D Error] something\x1b[0;m"))
    err = capsys.readouterr().err
    assert "error: [Open3D Error] something" in err and "\x1b" not in err


def test_wording_one_frame_and_a_missing_path(tmp_path):
    """'1 frame', not '1 frames'; `slam eval` on a path that does not exist says so (it said
    'not a folder')."""
    from slam.pipeline import summary_line

    m = {"frames": 1, "fps": 2.0, "lost_frames": [], "frames_skipped": 0,
         "relocalisations": 0, "loops_accepted": 0}  # fmt: skip
    assert summary_line(m).startswith("1 frame, 2.0 fps")
    assert summary_line({**m, "frames": 3}).startswith("3 frames, ")
    res = runner.invoke(app, ["eval", str(tmp_path / "nope")])
    assert res.exit_code == 2
    assert f"{tmp_path / 'nope'} not found" in flat(res.output)
