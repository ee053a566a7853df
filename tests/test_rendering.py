"""Tests of aasoatt_env.sim.rendering and aasoatt_env.analysis.plotting (headless)."""

from __future__ import annotations

import subprocess
import sys
import warnings

import numpy as np
import pytest

from aasoatt_env.errors import ConfigError

pytest.importorskip("pygame")

from aasoatt_env.sim.rendering import BACKGROUND, Frame, Renderer, robot_colors, save_animation  # noqa: E402

BOUNDS = (-5.0, 5.0, -5.0, 5.0)


def ring_frame(n: int = 4, **kw) -> Frame:
    ang = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    pos = 3.0 * np.c_[np.cos(ang), np.sin(ang)]
    defaults = dict(positions=pos, headings=ang + np.pi, radii=np.full(n, 0.48), world_bounds=BOUNDS)
    defaults.update(kw)
    return Frame(**defaults)


def to_pixel(p, width=200, height=200, bounds=BOUNDS):
    xmin, xmax, ymin, ymax = bounds
    scale = min(width / (xmax - xmin), height / (ymax - ymin))
    return int(round((p[1] - ymin) * -scale + height)), int(round((p[0] - xmin) * scale))


# ----------------------------------------------------------------------------- Renderer


def test_rgb_array_shape_dtype_and_robot_colour():
    frame = ring_frame(4)
    img = Renderer(width=240, height=200).rgb_array(frame)
    assert img.shape == (200, 240, 3)
    assert img.dtype == np.uint8
    img = Renderer(200, 200).rgb_array(frame)
    colors = robot_colors(4)
    for i in range(4):
        # Half a radius behind the centre: inside the disc, off the heading line.
        back = frame.positions[i] - 0.25 * np.array([np.cos(frame.headings[i]), np.sin(frame.headings[i])])
        row, col = to_pixel(back)
        assert tuple(img[row, col]) == tuple(colors[i]), i


def test_empty_frame_is_background():
    empty = Frame(positions=np.zeros((0, 2)), headings=[], radii=[], world_bounds=BOUNDS)
    img = Renderer(64, 48, grid=False, show_text=False).rgb_array(empty)
    assert img.shape == (48, 64, 3)
    assert np.all(img == np.array(BACKGROUND, dtype=np.uint8))
    # With grid and text, still mostly background.
    img = Renderer(64, 48).rgb_array(empty)
    assert np.mean(np.all(img == np.array(BACKGROUND), axis=2)) > 0.5


def test_robots_change_picture_and_are_distinct():
    r = Renderer(120, 120, grid=False, show_text=False)
    img = r.rgb_array(ring_frame(6))
    assert np.mean(np.any(img != np.array(BACKGROUND), axis=2)) > 0.02
    colors = robot_colors(30)
    assert len({tuple(c) for c in colors}) == 30


def test_all_features_draw_without_error():
    n, t = 5, 30
    base = ring_frame(n)
    trails = np.linspace(1.0, 1.3, t)[:, None, None] * base.positions[None]
    trails[10, 2] = np.nan  # a gap in one trail
    frame = ring_frame(
        n,
        references=0.9 * base.positions,
        goals=-base.positions,
        obstacle_centers=[[0.0, 0.0], [1.0, -1.0]],
        obstacle_radii=[0.8, 0.3],
        trails=trails,
        avoiding=[True, False, True, False, False],
        sensing_range=1.5,
        time=3.25,
        title="test",
    )
    r = Renderer(160, 160)
    img = r.rgb_array(frame)
    assert img.shape == (160, 160, 3)
    # Obstacle at the origin is grey.
    row, col = to_pixel((0.0, 0.0), 160, 160)
    assert tuple(img[row, col]) == (140, 140, 140)
    # An avoiding robot has red on its rim.
    cx = frame.positions[0]
    row, col = to_pixel(cx + np.array([0.46, 0.0]), 160, 160)
    window = img[row - 2 : row + 3, col - 2 : col + 3].reshape(-1, 3)
    assert any(p[0] > 180 and p[1] < 80 and p[2] < 80 for p in window)
    # Auto bounds, robots off-screen and a single-point trail do not crash.
    r.rgb_array(Frame(positions=[[100.0, 0.0]], headings=[0.0], radii=[0.5], world_bounds=BOUNDS))
    r.rgb_array(Frame(positions=[[1.0, 2.0]], headings=[0.0], radii=0.5, trails=[[[1.0, 2.0]]]))
    r.rgb_array(ring_frame(3, world_bounds=None, obstacle_centers=[[9.0, 9.0]], obstacle_radii=[1.0]))


def test_a_busy_frame_renders_the_same_picture_every_time():
    frame = ring_frame(
        20,
        trails=np.linspace(1.0, 1.2, 100)[:, None, None] * ring_frame(20).positions,
        references=np.zeros((20, 2)),
        goals=np.zeros((20, 2)),
        avoiding=np.ones(20, bool),
    )
    r = Renderer()
    first = r.rgb_array(frame)
    assert first.shape == (600, 600, 3)
    np.testing.assert_array_equal(r.rgb_array(frame), first)  # the surface is cleared between frames
    np.testing.assert_array_equal(Renderer().rgb_array(frame), first)


def test_frame_validation():
    with pytest.raises(ConfigError, match="positions"):
        Frame(positions=np.zeros((3, 3)), headings=np.zeros(3), radii=np.ones(3))
    with pytest.raises(ConfigError, match="references"):
        ring_frame(3, references=np.zeros((2, 2)))
    with pytest.raises(ConfigError, match="world_bounds"):
        ring_frame(3, world_bounds=(1.0, 0.0, 0.0, 1.0))
    with pytest.raises(ConfigError, match="trails"):
        ring_frame(3, trails=np.zeros((4, 2, 2)))
    with pytest.raises(ConfigError):
        Renderer(0, 10)


def test_human_mode_headless_warns_once_and_never_raises(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    r = Renderer(80, 80)
    with pytest.warns(RuntimeWarning, match="no display"):
        r.show(ring_frame(2))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r.show(ring_frame(2))  # second call: silent
    r.close()
    r.close()
    with Renderer(40, 40) as r2, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r2.show(ring_frame(1))


def test_human_mode_unreachable_display_warns(monkeypatch):
    # A DISPLAY that cannot be reached: SDL either fails or falls back to an invisible driver.
    monkeypatch.setenv("DISPLAY", ":987")
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.delenv("SDL_VIDEODRIVER", raising=False)
    r = Renderer(40, 40)
    with pytest.warns(RuntimeWarning, match="no display"):
        r.show(ring_frame(2))
    r.close()


# ----------------------------------------------------------------------------- animations


def test_gif_written_and_readable(tmp_path):
    iio = pytest.importorskip("imageio.v3")
    r = Renderer(64, 64)
    frames = [r.rgb_array(ring_frame(3, time=0.1 * k, headings=np.full(3, 0.3 * k))) for k in range(5)]
    out = save_animation(frames, tmp_path / "sub" / "anim.gif", fps=10)
    assert out.exists() and out.stat().st_size > 0
    back = iio.imread(out, index=None)
    assert back.shape[0] == 5
    assert back.shape[1:3] == (64, 64)


def test_save_animation_errors(tmp_path, monkeypatch):
    pytest.importorskip("imageio")
    frame = np.zeros((8, 8, 3), np.uint8)
    with pytest.raises(ConfigError, match="suffix"):
        save_animation([frame], tmp_path / "a.txt")
    with pytest.raises(ConfigError, match="no frames"):
        save_animation([], tmp_path / "a.gif")
    with pytest.raises(ConfigError, match="shape"):
        save_animation([frame, np.zeros((9, 8, 3), np.uint8)], tmp_path / "a.gif")
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    with pytest.raises(ImportError, match=r"imageio-ffmpeg.*\.gif"):
        save_animation([frame], tmp_path / "a.mp4")


def test_mp4_if_ffmpeg_available(tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    frames = [np.full((31, 33, 3), 20 * k, np.uint8) for k in range(4)]
    out = save_animation(frames, tmp_path / "a.mp4", fps=5)
    assert out.stat().st_size > 0


# ----------------------------------------------------------------------------- missing dependencies


@pytest.mark.parametrize("module", ["pygame"])
def test_renderer_missing_dependency_message(monkeypatch, module):
    monkeypatch.setitem(sys.modules, module, None)
    with pytest.raises(ImportError, match=r'pip install "aasoatt\[render\]"'):
        Renderer()


def test_save_animation_missing_imageio_message(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "imageio", None)
    monkeypatch.setitem(sys.modules, "imageio.v3", None)
    with pytest.raises(ImportError, match=r'pip install "aasoatt\[render\]"'):
        save_animation([np.zeros((4, 4, 3), np.uint8)], tmp_path / "a.gif")


def test_plotting_missing_matplotlib_message(monkeypatch):
    from aasoatt_env.analysis import plotting

    for name in ("matplotlib", "matplotlib.figure", "matplotlib.backends.backend_agg"):
        monkeypatch.setitem(sys.modules, name, None)
    with pytest.raises(ImportError, match=r'pip install "aasoatt\[render\]"'):
        plotting.plot_velocity_profile([0.0, 1.0], [[0.0], [1.0]])


def test_modules_import_without_optional_dependencies():
    code = (
        "import sys\n"
        "for m in ('pygame', 'matplotlib', 'imageio', 'PIL'): sys.modules[m] = None\n"
        "import aasoatt_env.sim.rendering, aasoatt_env.analysis.plotting\n"
        "print('ok')\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert "ok" in res.stdout


# ----------------------------------------------------------------------------- plots


@pytest.fixture
def run_data():
    t_len, n = 60, 4
    times = np.linspace(0.0, 6.0, t_len)
    ang = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    start = 4.0 * np.c_[np.cos(ang), np.sin(ang)]
    s = np.linspace(0.0, 1.0, t_len)[:, None, None]
    refs = start * (1.0 - 2.0 * s)
    pos = refs + 0.5 * np.sin(np.pi * s) * np.c_[-np.sin(ang), np.cos(ang)]
    return times, pos, refs, -start


def test_png_plots_written(tmp_path, run_data):
    pytest.importorskip("matplotlib")
    from aasoatt_env.analysis.plotting import (
        plot_distance_profile,
        plot_snapshots,
        plot_trajectories,
        plot_velocity_profile,
    )

    times, pos, refs, goals = run_data
    n = pos.shape[1]
    obstacles = (np.array([[0.0, 1.5]]), np.array([0.4]))
    d = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)
    iu = np.triu_indices(n, 1)
    pairs = d[:, iu[0], iu[1]]
    speeds = np.linalg.norm(np.gradient(pos, times, axis=0), axis=-1)
    outputs = {
        "traj.png": lambda p: plot_trajectories(pos, 0.48, refs, goals, obstacles, path=p, title="t"),
        "traj_min.png": lambda p: plot_trajectories(pos, path=p),
        "dist.png": lambda p: plot_distance_profile(times, pairs.min(axis=1), 0.96, path=p),
        "dist_pairs.png": lambda p: plot_distance_profile(times, pairs, 0.96, path=p),
        "vel.png": lambda p: plot_velocity_profile(times, speeds, path=p, max_speed=3.0),
        "snap.png": lambda p: plot_snapshots(
            pos, times, [0, 20, -1], 0.48, np.array([[0.0, 1.5, 0.4]]), path=p, references=refs, goals=goals
        ),
    }
    for name, make in outputs.items():
        path = tmp_path / name
        fig = make(path)
        assert path.exists() and path.stat().st_size > 1000, name
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert fig.axes


def test_plot_validation(run_data):
    pytest.importorskip("matplotlib")
    from aasoatt_env.analysis.plotting import plot_distance_profile, plot_snapshots, plot_trajectories

    times, pos, refs, _ = run_data
    with pytest.raises(ConfigError, match="positions"):
        plot_trajectories(pos[0])
    with pytest.raises(ConfigError, match="min_distance"):
        plot_distance_profile(times, np.zeros(3), 0.96)
    with pytest.raises(ConfigError, match="indices"):
        plot_snapshots(pos, times, [999], 0.48)
    with pytest.raises(ConfigError, match="obstacles"):
        plot_trajectories(pos, obstacles=np.zeros((2, 2)))


def test_plotting_leaves_pyplot_alone(run_data):
    plt = pytest.importorskip("matplotlib.pyplot")
    from aasoatt_env.analysis.plotting import plot_trajectories

    before = plt.get_fignums()
    plot_trajectories(run_data[1])
    assert plt.get_fignums() == before
