"""The compiled kernels: made ready before the first frame, cached, and cached outside a
read-only package folder."""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

from slam import kernels

ROOT = Path(__file__).resolve().parents[1]


def test_prepare_leaves_every_kernel_cached():
    kernels.prepare()
    assert kernels.cached()
    # loaded, not compiled again (measured: 0.001 s; 3.9 s compiling)
    assert kernels.prepare() < 1.0


def test_a_read_only_package_folder_caches_in_the_user_cache(tmp_path):
    """numba writes its cache next to the module, or in the user's cache folder when the
    package folder cannot be written: the joint alignment's kernels imported from a read-only
    copy compile there, and a second process loads them from there."""
    pkg = tmp_path / "ro"
    pkg.mkdir()
    shutil.copy(ROOT / "slam" / "frontend" / "joint_kernels.py", pkg / "kernels_copy.py")
    # read-only, and a file where numba would make its __pycache__ folder: root (CI) may
    # write into a read-only folder, but not make a folder where a file is
    (pkg / "__pycache__").write_text("")
    pkg.chmod(stat.S_IRUSR | stat.S_IXUSR)
    cache = tmp_path / "cache"
    code = (
        "import numpy as np, kernels_copy as k\n"
        "J, r = np.ones((8, 6), np.float32), np.ones(8, np.float32)\n"
        "k.weighted_system(J, r, 8, 0.0, 1.0, 1.0, 1.0)\n"
        "print(k.weighted_system.stats.cache_hits)\n"
    )
    env = dict(os.environ, PYTHONPATH=str(pkg), XDG_CACHE_HOME=str(cache), HOME=str(tmp_path))
    env.pop("NUMBA_CACHE_DIR", None)
    try:
        runs = [
            subprocess.run(
                [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300
            )
            for _ in range(2)
        ]
    finally:
        pkg.chmod(stat.S_IRWXU)
    for r in runs:
        assert r.returncode == 0, r.stderr[-2000:]
    assert sorted(p.name for p in pkg.iterdir()) == ["__pycache__", "kernels_copy.py"]
    assert list(cache.glob("**/*kernels_copy*weighted_system*.nbi"))
    assert runs[1].stdout.strip() != "Counter()"  # the second process loaded it
