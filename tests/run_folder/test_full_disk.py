"""A full disk (ENOSPC) loses nothing silently: a mesh Open3D cut short is never renamed into
place, a failed checkpoint leaves no temporary file and the run goes on, and a result that
cannot be written is a clear error without metrics.json."""

from __future__ import annotations

import errno
import logging

import open3d as o3d
import pytest

import slam
from slam.mapping import tsdf
from slam.run_folder import METRICS_FILE, checkpoint
from slam.run_folder.layout import CHECKPOINT_DIR


def _mesh() -> o3d.geometry.TriangleMesh:
    return o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0)


def test_a_whole_mesh_is_written_and_its_size_checks(tmp_path):
    tsdf.write_mesh(tmp_path / "m.ply", _mesh())
    back = o3d.io.read_triangle_mesh(str(tmp_path / "m.ply"))
    assert len(back.vertices) == 8 and len(back.triangles) == 12
    assert tsdf._ply_size(tmp_path / "m.ply") == (tmp_path / "m.ply").stat().st_size


def test_a_truncated_mesh_is_never_renamed_into_place(tmp_path, monkeypatch):
    real = o3d.io.write_triangle_mesh

    def short_write(path, mesh, **kw):  # what Open3D does on a full disk: "success"
        real(path, mesh, **kw)
        with open(path, "r+b") as f:
            f.truncate(f.seek(0, 2) - 40)
        return True

    monkeypatch.setattr(tsdf.o3d.io, "write_triangle_mesh", short_write)
    with pytest.raises(OSError, match="could not be written whole"):
        tsdf.write_mesh(tmp_path / "m.ply", _mesh())
    assert list(tmp_path.iterdir()) == []  # neither the mesh nor its temporary file


def _enospc(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def test_a_checkpoint_on_a_full_disk_leaves_no_temp_file_and_the_run_goes_on(
    synth_loop_320, tmp_path, monkeypatch, caplog
):
    real = checkpoint.np.savez
    calls = {"n": 0}

    def savez_then_fail(f, *args, **kwargs):  # the second checkpoint meets a full disk
        calls["n"] += 1
        if calls["n"] > 3:
            f.write(b"partial")
            _enospc()
        return real(f, *args, **kwargs)

    monkeypatch.setattr(checkpoint.np, "savez", savez_then_fail)
    with caplog.at_level(logging.WARNING):
        result, out = slam.run_sequence(synth_loop_320, tmp_path / "run", max_frames=30,
                                        checkpoint_every=10)  # fmt: skip
    assert result.metrics["frames"] == 30 and (out / METRICS_FILE).is_file()
    assert "not written" in caplog.text and "No space left" in caplog.text
    # an ERROR record: shown under --quiet too (it gave no word there)
    assert any(
        r.levelno == logging.ERROR and "not written" in r.getMessage() for r in caplog.records
    )
    assert not (out / CHECKPOINT_DIR).exists()  # removed with the work folders at the end
    assert not [p for p in out.rglob("*") if ".tmp" in p.name]


def test_results_that_cannot_be_written_are_a_clear_error(synth_loop_320, tmp_path, monkeypatch):
    monkeypatch.setattr("slam.run_folder.writer.write_tum", _enospc)
    with pytest.raises(slam.RunFolderError, match=f"No space left.*no {METRICS_FILE}"):
        slam.run_sequence(synth_loop_320, tmp_path / "run", max_frames=3)
    assert not (tmp_path / "run" / METRICS_FILE).exists()


def test_a_mesh_the_disk_cannot_take_leaves_a_folder_the_next_command_can_use(
    synth_loop_320, tmp_path, monkeypatch, caplog
):
    """It left the trajectories but removed config.yaml: `slam eval` said "not a run folder",
    --resume found no checkpoint and a rerun needed --overwrite. Without a checkpoint the
    folder is now left free for the rerun; with one, --resume writes the results."""
    from slam.run_folder import run_outputs

    monkeypatch.setattr(tsdf, "write_mesh", _enospc)
    with pytest.raises(slam.RunFolderError, match="No space left.*free space"):
        slam.run_sequence(synth_loop_320, tmp_path / "run", max_frames=8)
    assert run_outputs(tmp_path / "run") == []  # nothing a rerun must --overwrite
    with pytest.raises(slam.RunFolderError), caplog.at_level(logging.ERROR):
        slam.run_sequence(synth_loop_320, tmp_path / "ckpt", max_frames=12, checkpoint_every=5)
    assert (tmp_path / "ckpt" / CHECKPOINT_DIR).is_dir()  # resumable: kept
    monkeypatch.undo()
    slam.run_sequence(synth_loop_320, tmp_path / "run", max_frames=3)  # no --overwrite
    result, out = slam.resume_run(tmp_path / "ckpt")
    assert result.metrics["frames"] == 12 and (out / METRICS_FILE).is_file()
    assert (out / "mesh.ply").is_file() and not (out / CHECKPOINT_DIR).exists()
