"""The trajectory plot's choice of plane (slam.tools.plots)."""

import numpy as np

from slam.tools.plots import plot_plane


def test_plot_plane_choice():
    """The plane of the two largest extents; snapped to coordinate axes within 20 degrees and
    labelled; a tilted plane is labelled by its directions."""
    rng = np.random.default_rng(1)
    pl = plot_plane(rng.normal(size=(100, 3)) * [3.0, 0.1, 2.0])
    assert (pl.u_label, pl.v_label, pl.name) == ("x", "z", "x-z plane")  # floor, y-down camera
    pl = plot_plane(rng.normal(size=(100, 3)) * [0.1, 3.0, 2.0])
    assert (pl.u_label, pl.v_label) == ("y", "z")
    pl = plot_plane(rng.normal(size=(200, 3)) * [2.0, 3.0, 0.1])  # TUM: z is up
    assert (pl.u_label, pl.v_label, pl.name) == ("x", "y", "x-y plane")
    assert plot_plane(np.zeros((5, 3))).name == "x-z plane"
    # a plane tilted 45 degrees about x: not a coordinate plane, labelled by its directions
    t = rng.normal(size=(300, 2)) * [2.0, 1.0]
    c = np.sqrt(0.5)
    pts = np.stack([t[:, 0], c * t[:, 1], c * t[:, 1]], 1)
    pl = plot_plane(pts)
    assert pl.name == "plane of largest extent"
    assert pl.u_label == "x" and pl.v_label == "0.71 y + 0.71 z"
    u, v = pl.project(pts)
    np.testing.assert_allclose(np.hypot(u, v), np.linalg.norm(pts, axis=1), atol=1e-9)
