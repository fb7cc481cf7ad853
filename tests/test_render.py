"""The software renderer: particles appear where the camera sees them, outputs have the right frames."""

import os
import re
import textwrap

import numpy as np
import pytest
from PIL import Image

import warp_esph as we
from warp_esph import render as render_module
from warp_esph.cli import main
from warp_esph.meshes import lattice_points
from warp_esph.render import (BODY_PALETTE, Camera, Renderer, RenderOptions, UsdFrames, _linear, _to_srgb8, parse_frames,
                               render_usd)
from warp_esph.usd import surface_prim_path

W, H = 160, 120


def _srgb(c):
    return np.asarray(c) * 255.0


def write_clusters(path, centers, frames=1, spacing=0.02, ground=False, shift=(0.0, 0.0, 0.0), surface=False):
    """A USD file (UsdWriter) with one 5 x 5 x 5 cluster per centre, ``frames`` frames, each
    frame moved by ``shift`` from the last; no simulation."""
    b = we.SceneBuilder(spacing=spacing)
    mat = we.Material.preset("clay")
    for k, c in enumerate(centers):
        c = np.asarray(c, dtype=np.float64)
        b.add_particles(lattice_points(c - 2.5 * spacing, c + 2.5 * spacing, spacing), mat, name=f"cluster{k}")
    if ground:
        b.add_ground(height=-0.5)
    model = b.finalize()
    state = model.state()
    x0 = model.particle_x0.copy()
    alpha = np.linspace(0.0, 1.0, model.particle_count).astype(np.float32)
    state.alpha.assign(alpha)
    with we.UsdWriter(path, model, 10.0, surface=surface) as writer:
        for f in range(frames):
            state.x.assign((x0 + f * np.asarray(shift)).astype(np.float32))
            writer.write_frame(f, state)
    return model


def front_camera(ss=1):
    # From +z, looking at the origin: +x is to the right of the picture, +y up.
    return Camera(eye=(0.0, 0.0, 2.0), target=(0.0, 0.0, 0.0), width=W * ss, height=H * ss, fov=40.0)


def _pixel(img, x, y):
    return np.asarray(img, dtype=np.float64)[int(y), int(x)]


def test_clusters_appear_where_the_camera_sees_them(tmp_path):
    path = tmp_path / "two.usdc"
    # Body 0 left (x = -0.4), body 1 right (x = +0.4), both at the height of the eye.
    write_clusters(path, [(-0.4, 0.0, 0.0), (0.4, 0.0, 0.0)])
    data = UsdFrames(path)
    cam = front_camera()
    r = Renderer(data, data.frames, RenderOptions(width=W, height=H, supersample=1, label=False, shadows=False), camera=cam)
    img = r.render(0)
    assert img.size == (W, H) and img.mode == "RGB"
    px, py, _ = cam.project(np.array([[-0.4, 0.0, 0.0], [0.4, 0.0, 0.0]]))
    assert px[0] < W / 2 < px[1] and abs(py[0] - H / 2) < 1 and abs(py[1] - H / 2) < 1
    left, right = _pixel(img, px[0], py[0]), _pixel(img, px[1], py[1])
    # Body colours: palette 0 is orange (red > blue), palette 1 blue (blue > red).
    assert BODY_PALETTE[0][0] > BODY_PALETTE[0][2] and BODY_PALETTE[1][2] > BODY_PALETTE[1][0]
    assert left[0] > left[2] + 40, left
    assert right[2] > right[0] + 40, right
    # Background elsewhere: the centre, the corners and the top and bottom rows (a grey-blue gradient).
    background = [_pixel(img, W / 2, H / 2), _pixel(img, 2, 2), _pixel(img, W - 3, H - 3), _pixel(img, W / 2, 3)]
    for p in background:
        assert abs(p[0] - p[1]) < 25 and abs(p[1] - p[2]) < 25 and p.mean() > 180, p
    # Covered pixels: only around the two projected centres; a cluster is 0.1 m wide,
    # so it spans about focal * 0.1 / 2 pixels.
    arr = np.asarray(img, dtype=np.float64)
    covered = (np.abs(arr[..., 0] - arr[..., 2]) > 40)
    ys, xs = np.nonzero(covered)
    half = cam.focal * 0.06 / 2.0 + 2
    near_left = (np.abs(xs - px[0]) <= half) & (np.abs(ys - py[0]) <= half)
    near_right = (np.abs(xs - px[1]) <= half) & (np.abs(ys - py[1]) <= half)
    assert (near_left | near_right).all()
    assert near_left.sum() > 50 and near_right.sum() > 50


def test_nearer_cluster_hides_the_one_behind(tmp_path):
    path = tmp_path / "behind.usdc"
    # Body 0 behind (z = -0.5), body 1 in front (z = +0.5) on the same line of sight.
    write_clusters(path, [(0.0, 0.0, -0.5), (0.0, 0.0, 0.5)])
    data = UsdFrames(path)
    r = Renderer(data, data.frames, RenderOptions(width=W, height=H, supersample=1, label=False, shadows=False),
                 camera=front_camera())
    centre = _pixel(r.render(0), W / 2, H / 2)
    assert centre[2] > centre[0] + 40  # blue: body 1, the nearer one


def test_auto_camera_frames_every_frame(tmp_path):
    path = tmp_path / "moving.usdc"
    # Three frames of a cluster moving 0.5 m along x, over a ground plane; the camera fits all of them.
    write_clusters(path, [(0.0, 0.3, 0.0)], frames=3, ground=True, shift=(0.5, 0.0, 0.0))
    out = tmp_path / "sheet.png"
    result = render_usd(path, out, frames="all", width=W, height=H, supersample=1, label=False, columns=3)
    img = np.asarray(Image.open(out), dtype=np.float64)
    assert img.shape == (H, 3 * W, 3) and result.frames == [0, 1, 2]
    for k in range(3):
        tile = img[:, k * W:(k + 1) * W]
        orange = (tile[..., 0] - tile[..., 2]) > 60
        assert orange.sum() > 20, f"frame {k}: cluster not in the picture"
        ys, xs = np.nonzero(orange)
        assert xs.min() > 0 and xs.max() < W - 1 and ys.min() > 0 and ys.max() < H - 1  # not cut by the border
    # The cluster moves to the right from frame to frame.
    centres = [np.nonzero((img[:, k * W:(k + 1) * W, 0] - img[:, k * W:(k + 1) * W, 2]) > 60)[1].mean() for k in range(3)]
    assert centres[0] < centres[1] < centres[2]


def test_a_blown_up_body_is_left_out_of_the_framing(tmp_path):
    path = tmp_path / "blown.usdc"
    b = we.SceneBuilder(spacing=0.02)
    mat = we.Material.preset("clay")
    for k, c in enumerate([(-0.2, 0.0, 0.0), (0.2, 0.0, 0.0)]):
        c = np.asarray(c)
        b.add_particles(lattice_points(c - 0.05, c + 0.05, 0.02), mat, name=f"c{k}")
    model = b.finalize()
    state = model.state()
    x0 = model.particle_x0.copy()
    second = model.particle_body.numpy() == 1
    with we.UsdWriter(path, model, 10.0) as writer:
        writer.write_frame(0, state)
        x = x0.copy()
        x[second] = (x0[second] - (0.2, 0, 0)) * 1e6  # the second body blows up to a kilometre scale
        state.x.assign(x.astype(np.float32))
        writer.write_frame(1, state)
    lo, hi = UsdFrames(str(path)).bounds([0, 1])
    assert np.all(hi - lo < 1.0)  # framed on the body that is still there, not on the debris
    assert lo[0] == pytest.approx(-0.25, abs=0.03) and hi[0] == pytest.approx(0.25, abs=0.03)


def test_gif_folder_and_single_png_outputs(tmp_path):
    path = tmp_path / "anim.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=4, ground=True, shift=(0.0, -0.05, 0.0))
    gif = tmp_path / "anim.gif"
    result = render_usd(path, gif, width=W, height=H, supersample=1)
    assert result.kind == "gif"
    with Image.open(gif) as im:
        assert im.n_frames == 4 and im.size == (W, H)
        assert im.info.get("duration") == 100  # the file's 10 fps
    # A GIF stores centiseconds: at 30 fps one 33 ms duration was stored as 30 ms and played
    # 11 % fast; the frames' ends are rounded instead, so the rate holds on average. Above
    # 50 fps the frames would be shorter than viewers show: 20 ms, said in a warning.
    result = render_usd(path, gif, width=W, height=H, supersample=1, fps=30.0)
    with Image.open(gif) as im:
        durations = []
        for k in range(im.n_frames):
            im.seek(k)
            durations.append(im.info["duration"])
    assert durations == [30, 40, 30, 30] and abs(sum(durations) - 4 * 1000.0 / 30.0) < 10.0
    with pytest.warns(RuntimeWarning, match="fps = 60: a GIF's frames last at least 20 ms, so it plays at 50 fps, 0.83 x"):
        render_usd(path, gif, width=W, height=H, supersample=1, fps=60.0)
    folder = tmp_path / "frames"
    result = render_usd(path, folder, frames="1:3", width=W, height=H, supersample=1)
    assert sorted(os.listdir(folder)) == ["frame_00001.png", "frame_00002.png", "frame_00003.png"]
    for f in result.files:
        with Image.open(f) as im:  # closed: opened for its size alone, the file stayed open
            assert os.path.getsize(f) > 0 and im.size == (W, H)
    single = tmp_path / "last.png"
    result = render_usd(path, single, width=W, height=H, supersample=2)
    with Image.open(single) as im:
        assert result.frames == [3] and im.size == (W, H)


def test_color_by_primvar_draws_a_colour_bar(tmp_path):
    path = tmp_path / "alpha.usdc"
    write_clusters(path, [(0.0, 0.0, 0.0)])
    body = np.asarray(Image.open(render_usd(path, tmp_path / "b.png", width=W, height=H, supersample=1).output))
    alpha = np.asarray(Image.open(render_usd(path, tmp_path / "a.png", width=W, height=H, supersample=1, color="alpha").output))
    assert not np.array_equal(body, alpha)
    # The colour bar (viridis: yellow at the top, purple at the bottom) near the right edge.
    right = alpha[:, W - 20:].astype(np.float64)
    yellowish = (right[..., 0] > 180) & (right[..., 1] > 180) & (right[..., 2] < 100)
    purple = (right[..., 2] > right[..., 1] + 40) & (right[..., 0] > right[..., 1])
    assert yellowish.any() and purple.any()


def test_parse_frames():
    have = list(range(11))
    assert parse_frames(None, have) == have
    assert parse_frames("last", have) == [10] and parse_frames("first", have) == [0]
    assert parse_frames("-1", have) == [10] and parse_frames("3", have) == [3]
    assert parse_frames("0:10:5", have) == [0, 5, 10] and parse_frames(":2", have) == [0, 1, 2]
    assert parse_frames("1,4,-2", have) == [1, 4, 9]
    assert parse_frames("8:", have) == [8, 9, 10] and parse_frames("0:10:4", have) == [0, 4, 8]
    for past in ("0:11", "5:100:2", "3,9:12"):  # cut at frame 10 before, without a word
        with pytest.raises(ValueError, match=rf"^frames = '{past}' is not allowed: '{past.split(',')[-1]}' runs past the "
                                             r"file's last frame, 10: it holds 11 frames, 0\.\.10"):
            parse_frames(past, have)
    # A range starting past the end was told to end at frame 10 ('12:10' selects nothing).
    for late in ("12:20", "12:", "0,12:20:2"):
        with pytest.raises(ValueError, match=rf"^frames = '{late}' is not allowed: '{late.split(',')[-1]}' starts past the "
                                             r"file's last frame, 10: it holds 11 frames, 0\.\.10$"):
            parse_frames(late, have)
    # A range starting before the first frame was cut there without a word, as one past the end was.
    for early in ("0:6", ":6,0:4:2", "1:"):
        with pytest.raises(ValueError, match=rf"^frames = '{early}' is not allowed: '{early.split(',')[-1]}' starts before the "
                                             r"file's first frame, 2: it holds 5 frames, 2\.\.6; start the range at 2 or leave "
                                             r"its start out$"):
            parse_frames(early, [2, 3, 4, 5, 6])
    # A stepped one whose step misses the first frame: the advice keeps its frames (10, 20, ...
    # of '0:100:10'), where starting at the first frame, 1, would choose 1, 11, ...
    from_one = list(range(1, 101))
    with pytest.raises(ValueError, match=r"; start the range at 10, the first frame on its step from 1 on \(starting at 1 "
                                         r"would choose 1, 11, \.\.\.\)$"):
        parse_frames("0:100:10", from_one)
    assert parse_frames("10:100:10", from_one) == [f for f in range(0, 101, 10) if f >= 1]
    with pytest.raises(ValueError, match=r"^frames = '-20:' is not allowed: '-20:' counts back past the first frame "
                                         r"\(the file holds 0\.\.10, so -1 to -11\)$"):
        parse_frames("-20:", have)
    for bad in ("11", "x", "0:10:0", "", "1:2:3:4", "-0", "-0:5"):  # -0: frame 0 or the end? (read as 0)
        with pytest.raises(ValueError, match="frames"):
            parse_frames(bad, have)
    with pytest.raises(ValueError, match=r"frames = '-99' is not allowed: it counts back past the first frame "
                                         r"\(the file holds 0\.\.10, so -1 to -11\)"):
        parse_frames("-99", have)
    # Nothing to choose from (a mask file or target of no frame): an IndexError before.
    for spec in ("first", "last", "all", "0:3", [0]):
        with pytest.raises(ValueError, match=r"^--frames = .* is not allowed: there is no frame to choose from"):
            parse_frames(spec, [], "--frames")



def test_a_range_whose_step_is_not_above_0_is_refused_naming_the_step():
    """'0:10:0' and '10:0:-2' are of the form A:B:STEP, yet were refused as not being it ("'0:10:0'
    is not 'all', 'first', 'last', N, -N, A:B or A:B:STEP"), which left the user to guess what
    was wrong: the refusal names the step and what it must be."""
    have = list(range(11))
    for spec, part, step in (("0:10:0", "0:10:0", "0"), ("1,10:0:-2", "10:0:-2", "-2")):
        with pytest.raises(ValueError, match=rf"^--frames = '{spec}' is not allowed: '{part}' steps by {step}: the STEP of "
                                             r"A:B:STEP must be an integer >= 1 \(B included\)$"):
            parse_frames(spec, have, "--frames")
    assert parse_frames("0:10:3", have) == [0, 3, 6, 9]


def test_parse_frames_refusal_shows_numpy_integers_as_plain_ints():
    """Frames picked with numpy (``np.arange``, ``np.where``) were shown in the refusal as numpy
    writes them, ``frames = [np.int64(3), np.int64(99)]``: they are shown as the ints they are."""
    have = list(range(11))
    assert parse_frames([np.int64(3), np.int32(5)], have) == [3, 5]
    with pytest.raises(ValueError, match=r"^frames = \[3, 99\] is not allowed: frame 99 is not in the file \(it holds 0\.\.10\)$"):
        parse_frames([np.int64(3), np.int64(99)], have)
    with pytest.raises(ValueError, match=r"^frames = \(3, 'x'\) is not allowed: 'x' is not "):
        parse_frames((np.int16(3), "x"), have)
    with pytest.raises(ValueError, match=r"^frames = 99 is not allowed: frame 99 is not in the file"):
        parse_frames(np.int64(99), have)


def test_parse_frames_takes_a_range_a_numpy_array_or_an_iterator_as_the_renderer_does():
    """Only ``Renderer`` converted a range, a numpy array or an iterator of frame numbers;
    ``render_usd`` and ``export_frames``, which call ``parse_frames`` directly, refused them
    ('frames = array([0, 2]) is not allowed'). ``parse_frames`` converts them for every caller."""
    have = list(range(11))
    assert parse_frames(np.array([0, 2]), have) == [0, 2]
    assert parse_frames(range(1, 4), have) == [1, 2, 3]
    assert parse_frames(iter([10, 3]), have) == [10, 3]
    assert parse_frames(np.array(4), have) == [4]
    assert parse_frames(np.arange(0, 11, 5, dtype=np.int32), have) == [0, 5, 10]
    with pytest.raises(ValueError, match=r"^frames = \[3, 99\] is not allowed: frame 99 is not in the file \(it holds 0\.\.10\)$"):
        parse_frames(np.array([3, 99]), have)


def test_parse_frames_refuses_a_nested_list_or_a_2d_array_as_such():
    """A 2-D array or a list of lists was joined into one text and split at its commas, so the
    refusal named the value but blamed a fragment: ``'[0' is not 'all', ...``. It is refused as a
    nested entry; a 0-d array entry is still the number it holds."""
    have = list(range(11))
    for bad, shown in ((np.array([[0, 1]]), r"\[\[0, 1\]\]"), ([[0, 1], [2, 3]], r"\[\[0, 1\], \[2, 3\]\]"),
                       ([np.array([0, 1])], r"\[\[0, 1\]\]"), ([3, range(2)], r"\[3, range\(0, 2\)\]")):
        with pytest.raises(ValueError, match=rf"^frames = {shown} is not allowed: its entry \S.* is itself a sequence "
                                             r"\(a nested list or a 2-D array\); frames must be frame numbers, a range or 'all'"):
            parse_frames(bad, have)
    assert parse_frames([np.array(3), 5], have) == [3, 5]
    with pytest.raises(ValueError, match=r"^frames = 2\.5 is not allowed: give e\.g\. 'all'"):
        parse_frames(2.5, have)  # not iterable: refused by its value
    # An array's entries are shown as plain numbers, not numpy's reprs.
    with pytest.raises(ValueError, match=r"^frames = \[0\.5, 2\.0\] is not allowed: '0\.5' is not 'all'"):
        parse_frames(np.array([0.5, 2.0]), have)
    with pytest.raises(ValueError, match=r"^frames = \[\[0, 1\]\] is not allowed: "):
        parse_frames(np.array([[0, 1]]), have)

def test_bad_outputs(tmp_path, monkeypatch):
    path = tmp_path / "one.usdc"
    write_clusters(path, [(0.0, 0.0, 0.0)])
    with pytest.raises(ValueError, match=r"\.png, \.gif, \.mp4"):
        render_usd(path, tmp_path / "x.jpg")
    monkeypatch.setattr(render_module, "ffmpeg_path", lambda: None)
    with pytest.raises(ValueError, match="ffmpeg"):
        render_usd(path, tmp_path / "x.mp4")
    with pytest.raises(FileNotFoundError):
        render_usd(tmp_path / "missing.usdc", tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()
    # A rate no GIF holds (1e-9 fps ended in an OverflowError in the GIF writer) and a
    # folder in the way of the picture: refused before any frame is drawn.
    with pytest.raises(ValueError, match=r"fps = 1e-09 is not allowed: must be in \[0\.01, 1000\.0\]"):
        render_usd(path, tmp_path / "x.gif", fps=1e-9)
    (tmp_path / "d.png").mkdir()
    with pytest.raises(ValueError, match=r"output = .*d\.png' is not allowed: it is a folder; a file is written there"):
        render_usd(path, tmp_path / "d.png")
    # A zoom that overflowed the camera's distance, and a contact sheet too large to hold
    # (a million columns): refused by name before drawing, not a NaN or a MemoryError.
    with pytest.raises(ValueError, match=r"zoom = 1e\+308 is not allowed: must be in \[0\.001, 1000\.0\]"):
        render_usd(path, tmp_path / "z.png", zoom=1e308)
    many = tmp_path / "many.usdc"
    write_clusters(many, [(0.0, 0.0, 0.0)], frames=40)
    with pytest.raises(ValueError, match=r"40 frames of 8192 x 8192 in 4 columns .* more than 2e\+08 pixels"):
        render_usd(many, tmp_path / "s.png", frames="all", width=8192, height=8192)
    assert not (tmp_path / "z.png").exists() and not (tmp_path / "s.png").exists()
    render_usd(many, tmp_path / "s.png", frames="0,1", width=64, height=48, columns=10**6)
    with Image.open(tmp_path / "s.png") as im:
        assert im.size == (128, 48)  # two columns: no more than there are frames
    # A playback rate for pictures, columns for a movie or a folder: each was ignored.
    with pytest.raises(ValueError, match=r"fps = 10\.0 is not allowed with output = .*p\.png': it is the playback rate"):
        render_usd(path, tmp_path / "p.png", fps=10.0)
    with pytest.raises(ValueError, match=r"fps = 10\.0 is not allowed with output = .*': .* a folder of PNG frames has none"):
        render_usd(path, tmp_path / "frames", fps=10.0)
    with pytest.raises(ValueError, match=r"columns = 2 is not allowed with output = .*m\.gif': .* a \.gif holds them"):
        render_usd(path, tmp_path / "m.gif", columns=2)
    assert not (tmp_path / "p.png").exists() and not (tmp_path / "frames").exists() and not (tmp_path / "m.gif").exists()


def test_a_picture_or_gif_larger_than_the_memory_is_refused_before_anything_is_written(tmp_path, monkeypatch):
    """The drawing takes about 185 B a supersampled pixel (measured) and a GIF holds every
    frame until it is written: 8192 x 8192 at supersample 2 (some 50 GiB) was killed part
    way, as was a GIF of thousands of frames. Both are refused by name before any drawing,
    against the machine's memory (made 256 MiB here)."""
    path = tmp_path / "one.usdc"
    write_clusters(path, [(0.0, 0.0, 0.0)])
    monkeypatch.setattr(render_module, "_machine_memory", lambda: 2**28, raising=False)
    with pytest.raises(ValueError, match=r"^width x height = 1024 x 1024 at supersample = 2 is not allowed on this machine: "
                                         r"its 4\.19e\+06 pixels \(supersampled\) need about 0\.781 GiB \(200 B a pixel\), "
                                         r"more than the 0\.25 GiB available; use a smaller picture or supersample$"):
        render_usd(path, tmp_path / "big.png", width=1024, height=1024)
    with pytest.raises(ValueError, match=r"^width x height = 1024 x 1024 at supersample = 2 is not allowed"):
        Renderer(UsdFrames(path), None, RenderOptions(width=1024, height=1024))
    # A GIF may repeat a frame: 100 pictures of frame 0, each 4 MiB held (RGB and palette).
    with pytest.raises(ValueError, match=r"^frames = '(0,){28}\.\.\. is not allowed in one \.gif: 100 frames of 1024 x 1024 are held "
                                         r"together until it is written, about 0\.391 GiB, more than the 0\.25 GiB available; "
                                         r"choose fewer frames or a smaller picture, or write a folder or an \.mp4$"):
        render_usd(path, tmp_path / "long.gif", frames=",".join(["0"] * 100), width=1024, height=1024, supersample=1)
    assert not (tmp_path / "big.png").exists() and not (tmp_path / "long.gif").exists()
    render_usd(path, tmp_path / "short.gif", frames="0,0", width=1024, height=1024, supersample=1)
    with Image.open(tmp_path / "short.gif") as im:
        assert im.size == (1024, 1024)


def test_a_picture_is_weighed_against_the_containers_memory_limit(tmp_path, monkeypatch):
    """The renderer weighed a picture against the machine's memory, where a model and a
    rollout are weighed against the control group's limit where lower: in a container of 256
    MiB a picture of some 0.8 GiB was drawn until the container killed it."""
    from warp_esph import builder

    path = tmp_path / "one.usdc"
    write_clusters(path, [(0.0, 0.0, 0.0)])
    proc, root = tmp_path / "cgroup", tmp_path / "fs"
    root.mkdir()
    proc.write_text("0::/\n")
    (root / "memory.max").write_text(f"{2**28}\n")
    monkeypatch.setattr(builder, "_PROC_CGROUP", str(proc), raising=False)
    monkeypatch.setattr(builder, "_CGROUP_ROOT", str(root), raising=False)
    monkeypatch.setattr(builder, "_process_memory_limit", lambda: None)  # a ulimit of the runner's aside
    physical = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    # The machine's memory as if all of it were available (what other processes hold aside).
    monkeypatch.setattr(builder, "_machine_memory_free", lambda: physical)
    assert render_module._machine_memory() == min(physical, 2**28)
    with pytest.raises(ValueError, match=r"^width x height = 1024 x 1024 at supersample = 2 is not allowed on this machine: "
                                         r".*more than the 0\.25 GiB available; use a smaller picture or supersample$"):
        render_usd(path, tmp_path / "big.png", width=1024, height=1024)
    assert not (tmp_path / "big.png").exists()


def test_a_camera_renderer_or_particle_size_that_cannot_draw_is_refused_by_name(tmp_path):
    """A camera whose eye is its target, with a NaN or a fov of 0, or 1e300 m out, failed at
    the first frame ('cannot convert float NaN to integer', ZeroDivisionError); a camera
    that is none an AttributeError; radius_scale = 1e300 overflowed the float32 radii (NaN
    again). A Renderer of no frames framed the bounds of nothing and drew a picture of it,
    and one of a frame the file lacks failed only at its render."""
    path = tmp_path / "one.usdc"
    write_clusters(path, [(0.0, 0.0, 0.0)])
    data = UsdFrames(path)
    for kwargs, message in (
            (dict(eye=(0, 0, 0)), r"eye = \(0\.0, 0\.0, 0\.0\) is not allowed: it is the target; the camera looks from the "
                                  r"eye towards the target, so they must differ"),
            (dict(eye=(float("nan"), 0, 1)), r"eye\[0\] = nan is not allowed: must be a finite number"),
            (dict(fov=0.0), r"fov = 0\.0 is not allowed: must be > 0"),
            (dict(fov=170.0), r"fov = 170\.0 is not allowed: must be in \(0, 170\) degrees"),
            (dict(eye=(0, 0, 1e300)), r"eye = \(0\.0, 0\.0, 1e\+300\), target = \(0\.0, 0\.0, 0\.0\) are not allowed: "
                                      r"each coordinate must be within 1e\+15 m of the origin"),
            (dict(width=0), r"width = 0 is not allowed: must be an integer >= 1")):
        with pytest.raises(ValueError, match=f"^{message}$"):
            Camera(**{"eye": (0.0, 0.0, 2.0), "target": (0.0, 0.0, 0.0), "width": W, "height": H, **kwargs})
    o = RenderOptions(width=W, height=H, supersample=1)
    with pytest.raises(ValueError, match=r"^camera = 'front' is not allowed: must be a warp_esph\.render\.Camera or None$"):
        Renderer(data, [0], o, camera="front")
    with pytest.raises(ValueError, match=r"^frames = \[\] is not allowed: give e\.g\. 'all', 'last'"):
        Renderer(data, [], o)
    with pytest.raises(ValueError, match=r"^frames = \[5\] is not allowed: frame 5 is not in the file \(it holds 0\.\.0\)$"):
        Renderer(data, [5], o)
    with pytest.raises(ValueError, match=r"^radius_scale = 1e\+300 is not allowed: must be in \[0\.001, 1000\.0\]$"):
        render_usd(path, tmp_path / "r.png", radius_scale=1e300)
    assert not (tmp_path / "r.png").exists()
    img = Renderer(data, "all", o, camera=front_camera()).render(0)
    assert np.asarray(img).std() > 5.0  # the cluster against the background


def test_render_command(tmp_path, capsys):
    path = tmp_path / "cli.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=2, ground=True)
    assert main(["render", str(path), "-o", str(tmp_path / "out.gif"), "--width", "96", "--height", "72"]) == 0
    out = capsys.readouterr().out
    assert "out.gif" in out and "2 frames" in out and "s/frame" in out
    with Image.open(tmp_path / "out.gif") as im:
        assert im.n_frames == 2
    assert main(["render", str(path), "--width", "96", "--height", "72"]) == 0  # default: <file>.png, last frame
    assert (tmp_path / "cli.usdc.png").exists()
    assert main(["render", str(path), "-o", str(tmp_path / "o.png"), "--frames", "7"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("warp-esph: error: ") and "frame 7" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("options, message", [
    (["--zoom", "0"], "--zoom = 0.0 is not allowed: must be in [0.001, 1000.0]"),
    (["--supersample", "5"], "--supersample = 5 is not allowed: must be 1, 2, 3 or 4"),
    (["-o", "{d}/a.gif", "--fps", "0"], "--fps = 0.0 is not allowed: must be in [0.01, 1000.0]"),
    (["--radius-scale", "0"], "--radius-scale = 0.0 is not allowed"),
    (["--elevation", "95"], "--elevation = 95.0 is not allowed"),
    (["--azimuth", "nan"], "--azimuth = nan is not allowed"),
    (["--width", "10"], "--width x --height = 10 x 600 is not allowed"),
    (["--frames", "7"], "--frames = '7' is not allowed: frame 7 is not in the file"),
    # A range past the end was cut at the last frame without a word.
    (["--frames", "0:100"], "--frames = '0:100' is not allowed: '0:100' runs past the file's last frame, 1: it holds 2 "
                            "frames, 0..1; end the range at 1 or leave its end out"),
    (["-o", "{d}/a.png", "--fps", "10"], "--fps = 10.0 is not allowed with --output = '{d}/a.png'"),
    # No -o typed: the default output is said as such (it said "with --output = '.../cli.usdc.png'").
    (["--fps", "10"], "--fps = 10.0 is not allowed with the default output {d}/cli.usdc.png: it is the playback rate"),
    (["-o", "{d}/a.gif", "--columns", "2"], "--columns = 2 is not allowed with --output = '{d}/a.gif'"),
    # A sheet of one frame: the last frame was drawn alone, as without --columns, exit 0.
    (["-o", "{d}/a.png", "--columns", "2"], "--columns = 2 is not allowed with one frame: it lays several frames out side by "
                                            "side, and a .png without --frames is the last frame alone (frame 1); give --frames "
                                            "for several (e.g. --frames all)"),
    (["-o", "{d}/a.png", "--columns", "2", "--frames", "0"], "--columns = 2 is not allowed with one frame: it lays several "
                                                             "frames out side by side, and --frames = '0' chooses one (frame 0)"),
    (["-o", "{d}/a.obj"], "--output = '{d}/a.obj' is not allowed: the extension must be"),
])
def test_render_and_export_refusals_name_the_option_typed(tmp_path, capsys, options, message):
    """The library's checks named their parameters (``zoom = 0.0``, ``frames = '7'``), which
    the command does not have; the command names its own options."""
    from warp_esph.cli import main

    path = tmp_path / "cli.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=2)
    capsys.readouterr()
    assert main(["render", str(path), *(o.format(d=tmp_path) for o in options)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("warp-esph: error: " + message.format(d=tmp_path)) and err.count("\n") == 1, err
    if options[0] == "--frames":
        assert main(["export", str(path), *options]) == 2
        err = capsys.readouterr().err
        assert err.startswith("warp-esph: error: " + message) and err.count("\n") == 1, err
    assert sorted(os.listdir(tmp_path)) == ["cli.usdc"]


@pytest.mark.parametrize("frames", [[], ["--frames", "all"], ["--frames", "0"]], ids=["default", "all", "0"])
def test_render_columns_on_a_file_of_one_frame_says_so(tmp_path, capsys, frames):
    """``--columns`` on a file that holds one frame is refused saying so, not told to choose
    several: ``--frames all`` was told to give ``--frames all`` for several, which it had, and
    the default's advice (``--frames all``) was refused the same way."""
    from warp_esph.cli import main

    path = tmp_path / "one.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=1)
    capsys.readouterr()
    assert main(["render", str(path), "-o", str(tmp_path / "a.png"), "--columns", "2", *frames]) == 2
    err = capsys.readouterr().err
    assert err == ("warp-esph: error: --columns = 2 is not allowed with one frame: it lays several frames out side by side, "
                   "and the file holds one frame (frame 0); leave --columns out\n"), err
    assert sorted(os.listdir(tmp_path)) == ["one.usdc"]


def test_render_and_export_refuse_a_file_that_is_not_usd_by_its_name(tmp_path, capsys):
    """A scene file given where the USD output belongs was read by pxr, whose words named no
    format ("Cannot determine file format for @guess.toml@"): it is refused as not USD, with
    how a scene file runs; nothing is written."""
    from warp_esph.cli import main

    (tmp_path / "guess.toml").write_text("[scene]\n")
    (tmp_path / "frames.txt").write_text("1 2 3\n")
    for args in (["render", str(tmp_path / "guess.toml")], ["export", str(tmp_path / "guess.toml")],
                 ["render", str(tmp_path / "frames.txt")]):
        assert main(args) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "it is not a USD file (.usd, .usda, .usdc, .usdz)" in err, err
        assert ("'warp-esph run'" in err) == args[1].endswith(".toml"), err
    assert sorted(os.listdir(tmp_path)) == ["frames.txt", "guess.toml"]


@pytest.mark.skipif(render_module.ffmpeg_path() is None, reason="ffmpeg is not installed")
def test_mp4_with_ffmpeg(tmp_path):
    import subprocess

    path = tmp_path / "m.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=3, ground=True, shift=(0.0, -0.05, 0.0))
    out = tmp_path / "m.mp4"
    # An odd width and height (H.264 in yuv420p needs even ones) are padded by one pixel, the
    # last column and row repeated: they were cropped, the picture's edge dropped without a word.
    result = render_usd(path, out, width=W + 1, height=H + 1, supersample=1)
    assert result.kind == "mp4" and out.stat().st_size > 0
    # Decode with the same ffmpeg (ffprobe need not exist): its stream is W + 2 x H + 2, 3 frames,
    # and the particles moved between them (the clusters shift), so the frames differ (measured: mean
    # |frame 2 - frame 0| 24.9 levels; encoding noise of a still picture is far below 5).
    probe = subprocess.run([render_module.ffmpeg_path(), "-hide_banner", "-i", str(out)], capture_output=True).stderr.decode()
    assert re.search(r"Video: .*\b(\d+)x(\d+)\b", probe).groups() == (str(W + 2), str(H + 2)), probe
    raw = subprocess.run([render_module.ffmpeg_path(), "-v", "error", "-i", str(out), "-f", "rawvideo",
                          "-pix_fmt", "rgb24", "-"], capture_output=True, check=True).stdout
    assert W % 2 == 0 and len(raw) == 3 * (W + 2) * (H + 2) * 3
    frames = np.frombuffer(raw, np.uint8).reshape(3, H + 2, W + 2, 3).astype(float)
    assert np.abs(frames[2] - frames[0]).mean() > 5.0
    # Every drawn pixel is kept: frame 0 is the picture drawn at W + 1 x H + 1 (to the encoding's
    # noise: mean 2.2 levels measured; 5.2 against it moved by one column, 25 against frame 2),
    # its last column and row repeated (0.0 measured).
    drawn = np.asarray(Renderer(UsdFrames(path), [0, 1, 2], RenderOptions(width=W + 1, height=H + 1, supersample=1)).render(0),
                       dtype=float)
    assert np.abs(frames[0, :H + 1, :W + 1] - drawn).mean() < 3.5
    assert np.abs(frames[0, :, W + 1] - frames[0, :, W]).mean() < 3.0 and np.abs(frames[0, H + 1] - frames[0, H]).mean() < 3.0




@pytest.mark.skipif(render_module.ffmpeg_path() is None, reason="ffmpeg is not installed")
@pytest.mark.parametrize("name", ["take:1.mp4", "12:30.mp4"])
def test_an_mp4_named_with_a_colon_in_the_working_folder_is_written_there(tmp_path, monkeypatch, name):
    """ffmpeg reads what comes before a colon in a relative name as a protocol: 'take:1.mp4'
    failed with "Error opening output .take:1.<pid>.part.mp4: Protocol not found" (exit 2), a
    name the file system takes. The movie is handed to ffmpeg by its absolute path."""
    import subprocess

    write_clusters(tmp_path / "m.usdc", [(0.0, 0.2, 0.0)], frames=2, shift=(0.0, -0.05, 0.0))
    monkeypatch.chdir(tmp_path)
    result = render_usd("m.usdc", name, width=32, height=24, supersample=1)
    assert result.files == [name] and sorted(os.listdir(tmp_path)) == sorted(["m.usdc", name])
    raw = subprocess.run([render_module.ffmpeg_path(), "-v", "error", "-i", os.path.abspath(name), "-f", "rawvideo",
                          "-pix_fmt", "rgb24", "-"], capture_output=True, check=True).stdout
    assert len(raw) == 2 * 32 * 24 * 3  # both frames, whole
# ----------------------------------------------------------------------------- surfaces
BOX_TOML = textwrap.dedent(
    """
    [scene]
    name = "box"
    spacing = 0.04
    frames = 1

    [materials.soft]
    preset = "dough"

    [[bodies]]
    shape = "box"
    material = "soft"
    center = [0.0, 0.3, 0.0]
    size = [0.24, 0.2, 0.16]
    """
)


def _orange(img):
    a = np.asarray(img, dtype=np.float64)
    return (a[..., 0] - a[..., 2]) > 40


def _holes(mask):
    """Uncovered pixels that the background outside cannot reach (4-connected): see-through
    gaps enclosed by the silhouette."""
    outside = np.zeros_like(mask)
    outside[0, :], outside[-1, :], outside[:, 0], outside[:, -1] = (~mask[0, :], ~mask[-1, :], ~mask[:, 0], ~mask[:, -1])
    while True:
        grown = outside.copy()
        grown[1:] |= outside[:-1]
        grown[:-1] |= outside[1:]
        grown[:, 1:] |= outside[:, :-1]
        grown[:, :-1] |= outside[:, 1:]
        grown &= ~mask
        if np.array_equal(grown, outside):
            return ~mask & ~outside
        outside = grown


def test_run_with_surface_renders_a_closed_silhouette(tmp_path, capsys):
    scene = tmp_path / "box.toml"
    scene.write_text(BOX_TOML)
    usd = tmp_path / "box.usdc"
    assert main(["run", str(scene), "-o", str(usd), "--surface", "--preview", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "preview:" in out and "surfaces" in out
    assert UsdFrames(usd).has_surfaces
    # Looking along the lattice's z axis, between its columns of particles the background shows through.
    view = ["--frames", "0", "--azimuth", "0", "--elevation", "0", "--supersample", "1", "--width", "240", "--height", "180",
            "--no-label"]
    assert main(["render", str(usd), "-o", str(tmp_path / "surface.png"), *view]) == 0
    assert "(1 body as surfaces)" in capsys.readouterr().out
    assert main(["render", str(usd), "-o", str(tmp_path / "particles.png"), "--particles", *view]) == 0
    surface, particles = (_orange(Image.open(tmp_path / f"{n}.png")) for n in ("surface", "particles"))
    holes_surface, holes_particles = _holes(surface).sum(), _holes(particles).sum()
    assert holes_particles > 0.01 * particles.sum(), holes_particles  # the gaps the surface closes
    assert holes_surface == 0, holes_surface
    # The same body in the same place: the silhouettes overlap (the surface lies about half a spacing out).
    assert (surface & particles).sum() > 0.75 * particles.sum()


def _cube_file(tmp_path, half=0.3):
    """A cluster file whose body has, as its surface, a cube of quads with shared corners."""
    from pxr import Usd, UsdGeom, Vt

    path = tmp_path / "cube.usda"
    write_clusters(path, [(0.0, 0.0, 0.0)])
    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh.Define(stage, surface_prim_path(UsdFrames(path).bodies[0][0]))
    corners = np.array([[x, y, z] for x in (-half, half) for y in (-half, half) for z in (-half, half)], np.float32)
    # Outward quads (index = 4 x + 2 y + z over the corner signs).
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(corners))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([4] * 6))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([i for q in quads for i in q]))
    stage.GetRootLayer().Save()
    return path


def test_flat_cube_faces_have_the_key_lights_brightness(tmp_path):
    half = 0.3
    data = UsdFrames(_cube_file(tmp_path, half))
    v, tri = data.surface(0, 0)
    assert v.shape == (8, 3) and tri.shape == (12, 3)  # quads split in two
    cam = Camera(eye=(1.4, 1.1, 1.8), target=(0.0, 0.0, 0.0), width=W, height=H, fov=40.0)
    r = Renderer(data, data.frames, RenderOptions(width=W, height=H, supersample=1, label=False, shadows=False), camera=cam)
    img = np.asarray(r.render(0), dtype=np.float64)
    # Which face each pixel's ray meets first, by a ray-box test here.
    rays = cam.pixel_rays().reshape(-1, 3)
    with np.errstate(divide="ignore"):
        t1, t2 = (half - cam.eye) / rays, (-half - cam.eye) / rays
    tn, tf = np.minimum(t1, t2).max(axis=1), np.maximum(t1, t2).min(axis=1)
    hit = (tf >= tn) & (tn > 0)
    axis = np.minimum(t1, t2).argmax(axis=1)
    P = cam.eye + tn[:, None] * rays
    sign = np.sign(P[np.arange(len(P)), axis])
    face = np.where(hit, axis * 2 + (sign > 0), -1).reshape(H, W)
    # Coverage: the rasterised cube is where the rays meet the box (but for edge pixels).
    covered = np.abs(img - img[:, :1]).sum(axis=2) > 6  # the background is one colour per row
    assert (covered == (face >= 0)).mean() > 0.99
    brightness = {}
    for f in np.unique(face[face >= 0]):
        inner = face == f
        for _ in range(2):  # away from the edges
            inner = inner & np.roll(inner, 1, 0) & np.roll(inner, -1, 0) & np.roll(inner, 1, 1) & np.roll(inner, -1, 1)
        ys, xs = np.nonzero(inner)
        assert len(ys) > 100
        n = np.zeros(3)
        n[f // 2] = 1.0 if f % 2 else -1.0
        # The particles' lighting model, evaluated with the face's normal at each pixel.
        d = rays.reshape(H, W, 3)[ys, xs].astype(np.float32)
        eye_dir = -d / np.linalg.norm(d, axis=1, keepdims=True)
        base = np.broadcast_to(_linear(BODY_PALETTE[0]), (len(ys), 3)).astype(np.float32)
        ambient, key = r._shade_parts(base, np.broadcast_to(n.astype(np.float32), (len(ys), 3)).copy(), eye_dir, 0.25)
        expected = _to_srgb8(ambient + key).astype(np.float64)
        got = img[ys, xs]
        assert np.abs(got - expected).max() <= 2, (f, np.abs(got - expected).max())
        assert got.std(axis=0).max() < 3.0  # flat: one shade per face (the shared corners are not smoothed)
        brightness[f] = (float(n @ r.key), got.mean())
    assert len(brightness) == 3  # three faces seen from this corner
    # Relative brightness follows the key light: the face turned most towards it is the brightest.
    order_key = sorted(brightness, key=lambda f: brightness[f][0])
    order_seen = sorted(brightness, key=lambda f: brightness[f][1])
    assert order_key == order_seen, brightness


def test_frames_without_a_surface_render_particles(tmp_path):
    from pxr import Usd, UsdGeom, Vt

    path = tmp_path / "two.usda"
    write_clusters(path, [(0.0, 0.0, 0.0)], frames=2, surface=True, shift=(0.05, 0.0, 0.0))
    # Frame 1's surface empty, as the writer leaves it where no surface could be built.
    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath(surface_prim_path(UsdFrames(path).bodies[0][0])))
    mesh.GetPointsAttr().Set(Vt.Vec3fArray(), 1)
    mesh.GetFaceVertexCountsAttr().Set(Vt.IntArray(), 1)
    mesh.GetFaceVertexIndicesAttr().Set(Vt.IntArray(), 1)
    stage.GetRootLayer().Save()
    data = UsdFrames(path)
    assert data.has_surfaces and data.surface(0, 0) is not None and data.surface(1, 0) is None
    opts = dict(width=W, height=H, supersample=1, label=False, shadows=False)
    cam = front_camera()
    with_surface = Renderer(data, data.frames, RenderOptions(**opts), camera=cam)
    particles = Renderer(data, data.frames, RenderOptions(**opts, surfaces=False), camera=cam)
    assert list(with_surface.surfaces(0)) == [0] and with_surface.surfaces(1) == {}
    assert np.array_equal(np.asarray(with_surface.render(1)), np.asarray(particles.render(1)))
    surf0, part0 = np.asarray(with_surface.render(0)), np.asarray(particles.render(0))
    assert not np.array_equal(surf0, part0)
    assert _orange(surf0).sum() > 50 and _orange(part0).sum() > 50
    with pytest.raises(ValueError, match="surfaces"):
        RenderOptions(surfaces="yes")


def test_a_surface_without_a_sample_at_a_frame_is_not_the_last_one_held(tmp_path):
    """A file written with surfaces and continued without them (``UsdWriter(append=True)``,
    surface=False) holds surfaces up to the resume only: USD answers a later frame with the
    last sample held, and the body was drawn there as its surface of frame 1, standing still
    while its particles moved on. A frame where the surface has no sample of its own has no
    surface (as a body's points without a sample are not drawn), and the particles are drawn."""
    b = we.SceneBuilder(spacing=0.02)
    b.add_particles(lattice_points(np.full(3, -0.05), np.full(3, 0.05), 0.02), we.Material.preset("clay"))
    model = b.finalize()
    state = model.state()
    x0 = model.particle_x0.copy()
    path = tmp_path / "resumed.usda"

    def write(frames, **kw):
        with we.UsdWriter(path, model, 10.0, **kw) as w:
            for f in frames:
                state.x.assign((x0 + [0.1 * f, 0.0, 0.0]).astype(np.float32))
                w.write_frame(f, state)

    write(range(3), surface=True)
    write(range(2, 5), append=True)  # resumed at frame 2 without surfaces
    data = UsdFrames(path)
    assert data.has_surfaces
    for f in data.frames:
        mesh = data.surface(f, 0)
        assert (mesh is not None) == (f < 2), f
        if mesh is not None:  # a frame's surface surrounds that frame's particles
            assert np.mean(mesh[0], axis=0)[0] == pytest.approx(np.mean(data.arrays(f)["points"], axis=0)[0], abs=1e-3)
    opts = dict(width=W, height=H, supersample=1, label=False, shadows=False)
    cam = front_camera()
    drawn = Renderer(data, data.frames, RenderOptions(**opts), camera=cam)
    particles = Renderer(data, data.frames, RenderOptions(**opts, surfaces=False), camera=cam)
    assert drawn.surfaces(4) == {} and list(drawn.surfaces(1)) == [0]
    assert np.array_equal(np.asarray(drawn.render(4)), np.asarray(particles.render(4)))


def test_triangles_cover_exactly_the_pixel_centres_inside_and_depth_is_the_plane():
    from warp_esph.render import raster_triangles

    rng = np.random.default_rng(3)
    cam = front_camera()
    for _ in range(5):
        # A tilted quad as two triangles, a random fan of triangles inside it sharing its centre.
        c = rng.uniform(-0.2, 0.2, 3)
        a, b = rng.normal(size=3), rng.normal(size=3)
        a, b = 0.3 * a / np.linalg.norm(a), 0.3 * b / np.linalg.norm(b)
        quad = np.array([c - a - b, c + a - b, c + a + b, c - a + b, c])
        tris = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
        px, py, z = cam.project(quad)
        pix, dep, bary, who = raster_triangles(px, py, z, tris, W, H)
        # Every pixel centre inside the projected quad once (or twice on a shared edge), none outside.
        i, j = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
        corners = np.stack([px[:4], py[:4]], axis=1)
        def side(k):  # z of (edge k) x (pixel centre - its start)
            (x0, y0), (x1, y1) = corners[k], corners[(k + 1) % 4]
            return (x1 - x0) * (j - y0) - (y1 - y0) * (i - x0)

        edge = [side(k) for k in range(4)]
        inside = (np.all([e > 1e-3 for e in edge], axis=0) | np.all([e < -1e-3 for e in edge], axis=0)).reshape(-1)
        border = (np.min(np.abs(edge), axis=0) <= 1e-3).reshape(-1)
        hits = np.bincount(pix, minlength=W * H)
        assert (hits[inside] >= 1).all() and (hits[~inside & ~border] == 0).all()
        # Depth: where the pixel's ray meets the quad's plane (perspective-correct interpolation).
        n = np.cross(a, b)
        rays = cam.pixel_rays().reshape(-1, 3)[pix]
        expected = (n @ (c - cam.eye)) / (rays @ n)
        assert np.allclose(dep, expected, rtol=1e-4, atol=1e-5)
        # Barycentrics put the fragment on the triangle: the interpolated point is on the ray.
        P = np.einsum("nk,nkj->nj", bary, quad[tris[who]])
        assert np.allclose(P, cam.eye + dep[:, None] * rays, atol=1e-4)


# ----------------------------------------------------------------------------- tools
def _write_tool_file(path, add_tool, frames=9, fps=10.0, cluster=(0.0, 0.0, 5.0), ground=None):
    """A USD file of a model with the tools ``add_tool(builder)`` adds and a particle cluster
    at ``cluster`` (by default behind the front camera), each frame at time ``frame / fps``:
    the tools' poses come from their motions; no simulation."""
    b = we.SceneBuilder(spacing=0.02)
    c = np.asarray(cluster, dtype=np.float64)
    b.add_particles(lattice_points(c - 0.05, c + 0.05, 0.02), we.Material.preset("clay"), name="cluster")
    if ground is not None:
        b.add_ground(ground)
    add_tool(b)
    model = b.finalize()
    state = model.state()
    with we.UsdWriter(path, model, fps) as writer:
        for f in range(frames):
            state.time = f / fps
            writer.write_frame(f, state)
    return model


def _rot(q):
    from warp_esph.usd import quat_matrix
    return quat_matrix(q)


def _sphere_points(center, r, n=4000):
    """Points on a sphere (a Fibonacci lattice): their projected bounds are the silhouette's."""
    k = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * k / n)
    th = np.pi * (1 + 5**0.5) * k
    return np.asarray(center) + r * np.stack([np.cos(th) * np.sin(phi), np.cos(phi), np.sin(th) * np.sin(phi)], axis=1)


def _silhouette_points(kind):
    """The shape's surface points in the tool's frame, from its parameters (not the renderer's
    tessellation)."""
    if kind == "box":
        return np.array([[x, y, z] for x in (-0.15, 0.15) for y in (-0.08, 0.08) for z in (-0.1, 0.1)])
    if kind == "sphere":
        return _sphere_points((0, 0, 0), 0.12)
    a = np.linspace(0, 2 * np.pi, 721)
    ring = np.stack([0.08 * np.cos(a), np.zeros_like(a), 0.08 * np.sin(a)], axis=1)
    if kind == "cylinder":
        return np.concatenate([ring + (0, 0.15, 0), ring - (0, 0.15, 0)])
    if kind == "capsule":
        return np.concatenate([_sphere_points((0, 0.15, 0), 0.08), _sphere_points((0, -0.15, 0), 0.08)])
    from warp_esph.tools import blade_mesh
    return blade_mesh(0.3, 0.2, 0.05)[0]


def _add_moving_tool(kind):
    from warp_esph import tools
    shape = {"box": dict(half_extents=(0.15, 0.08, 0.1)), "sphere": dict(radius=0.12),
             "cylinder": dict(radius=0.08, half_height=0.15), "capsule": dict(radius=0.08, half_height=0.15),
             "mesh": dict(mesh=tools.blade_mesh(0.3, 0.2, 0.05))}[kind]
    # From the left of the picture to the right, turning about z and x as it goes.
    motion = tools.Velocity((0.6, 0.1, 0.0), (0.4, 0.3, 1.2), position=(-0.3, -0.05, 0.0))
    return lambda b: b.add_tool(kind, name="tool", motion=motion, **shape)


@pytest.mark.parametrize("kind", ["box", "sphere", "cylinder", "capsule", "mesh"])
def test_a_moving_tool_is_drawn_where_its_pose_puts_it(tmp_path, kind):
    path = tmp_path / f"{kind}.usdc"
    model = _write_tool_file(path, _add_moving_tool(kind))
    data = UsdFrames(path)
    assert [t.name for t in data.tools] == ["tool"]
    cam = front_camera()
    renderer = Renderer(data, [0, 8], RenderOptions(width=W, height=H, supersample=1, label=False, shadows=False),
                        camera=cam)
    background = _to_srgb8(renderer._static()["background"]).reshape(H, W, 3).astype(np.int64)
    local = _silhouette_points(kind)
    boxes = []
    for f in (0, 8):
        img = np.asarray(renderer.render(f), dtype=np.int64)
        mask = np.abs(img - background).max(axis=2) > 6
        ys, xs = np.nonzero(mask)
        # The pose the motion gives at this frame's time (the model's own evaluation).
        p, q = model.tools.pose_at(0, f / 10.0)
        px, py, _ = cam.project(local @ _rot(q).T + p)
        # Drawn pixel centres lie inside the silhouette's projected bounds (nothing is drawn
        # elsewhere), and reach them to within 2 px (a wedge's sharp edge is thinner than a
        # pixel at its tip; a polygon within 0.2 % of a sphere's radius).
        lo, hi = np.array([px.min(), py.min()]), np.array([px.max(), py.max()])
        got_lo, got_hi = np.array([xs.min(), ys.min()]) + 0.5, np.array([xs.max(), ys.max()]) + 0.5
        assert (got_lo >= lo - 0.05).all() and (got_hi <= hi + 0.05).all(), (kind, f, got_lo, got_hi, lo, hi)
        assert (got_lo - lo < 2.0).all() and (hi - got_hi < 2.0).all(), (kind, f, got_lo, got_hi, lo, hi)
        boxes.append((xs.min(), xs.max()))
        # Tool pixels are the tool's grey, not a particle's orange.
        mean = img[mask].mean(axis=0)
        assert abs(mean[0] - mean[2]) < 40 and mean[2] >= mean[0] - 5, mean
    assert boxes[1][0] > boxes[0][1], "the tool moved right across the picture by more than its width"


def test_a_plane_tool_is_drawn_as_the_plane_collider_at_its_pose(tmp_path):
    from warp_esph import tools
    # A floor tool rising from y = -0.2 at 0.1 m/s: at t = 0.8 s it is the plane y = -0.12.
    _write_tool_file(tmp_path / "tool.usdc", lambda b: b.add_tool("plane", name="floor", position=(0.0, -0.2, 0.0),
                                                                    motion=tools.Velocity((0.0, 0.1, 0.0))),
                     cluster=(0.0, 0.0, 0.0))
    for h in (-0.2, -0.12):
        _write_tool_file(tmp_path / f"static{h}.usdc", lambda b: None, cluster=(0.0, 0.0, 0.0), ground=h)
    cam = Camera(eye=(0.0, 0.6, 2.0), target=(0.0, 0.0, 0.0), width=W, height=H, fov=40.0)
    opts = RenderOptions(width=W, height=H, supersample=1, label=False)

    def picture(name, frame):
        data = UsdFrames(tmp_path / name)
        return np.asarray(Renderer(data, [frame], opts, camera=cam).render(frame), dtype=np.int64)

    low, high = picture("static-0.2.usdc", 8), picture("static-0.12.usdc", 8)
    assert np.abs(low - high).max() > 50  # the two heights differ in the picture
    assert np.array_equal(picture("tool.usdc", 0), low)
    assert np.array_equal(picture("tool.usdc", 8), high)
    # One renderer for both frames: the ray cast planes follow the tool (not kept from frame 0).
    both = Renderer(UsdFrames(tmp_path / "tool.usdc"), [0, 8], opts, camera=cam)
    assert np.array_equal(np.asarray(both.render(0), dtype=np.int64), low)
    assert np.array_equal(np.asarray(both.render(8), dtype=np.int64), high)


def _fake_ffmpeg(tmp_path, monkeypatch, body):
    """A stand-in ffmpeg: a shell script of ``body``, taken as the one on the PATH."""
    fake = tmp_path / "ffmpeg"
    fake.write_text(f"#!/bin/sh\n{body}\n")
    fake.chmod(0o755)
    monkeypatch.setattr(render_module, "ffmpeg_path", lambda: str(fake))


def test_an_ffmpeg_that_stops_early_is_its_error_not_a_closed_output(tmp_path, monkeypatch, capsys):
    """An ffmpeg that exits before taking the frames (no H.264 encoder): writing the small
    frames still buffered for its pipe raised BrokenPipeError, which the command read as its
    own output's reader gone (exit 141, no message) and which pointed the caller's stdout at
    /dev/null. Now ffmpeg's own message, exit 2, and the caller's stdout as it was."""
    _fake_ffmpeg(tmp_path, monkeypatch, "echo 'Unknown encoder libx264' >&2\nexit 1")
    path = tmp_path / "m.usdc"
    write_clusters(path, [(0.0, 0.0, 0.0)], frames=3)
    status = main(["render", str(path), "-o", str(tmp_path / "m.mp4"), "--frames", "all", "--width", "32", "--height", "24"])
    out, err = capsys.readouterr()
    assert status == 2, err
    assert err.count("\n") == 1 and "ffmpeg failed: Unknown encoder libx264" in err, err
    print("still here")
    assert capsys.readouterr().out == "still here\n"


def test_an_interrupted_movie_keeps_the_earlier_movie_and_leaves_no_part_file(tmp_path, monkeypatch):
    """An MP4 is written beside its name and renamed over it once ffmpeg has finished: ffmpeg
    wrote straight onto the output, so an interrupted render left a shorter movie over an
    earlier one. A stand-in ffmpeg (a shell script copying its input to the file it is given)
    shows where the frames go."""
    _fake_ffmpeg(tmp_path, monkeypatch, 'for out; do :; done\ncat > "$out"')
    path = tmp_path / "anim.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=3)
    out = tmp_path / "m.mp4"
    render_usd(path, out, frames="all", width=W, height=H, supersample=1)
    whole = out.read_bytes()
    assert len(whole) == 3 * W * H * 3  # the three frames' RGB, as piped
    real = render_module.Renderer.render
    calls = []

    def interrupted(self, f):
        calls.append(f)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(self, f)

    monkeypatch.setattr(render_module.Renderer, "render", interrupted)
    with pytest.raises(KeyboardInterrupt):
        render_usd(path, out, frames="all", width=W, height=H, supersample=1)
    assert out.read_bytes() == whole and sorted(os.listdir(tmp_path)) == ["anim.usdc", "ffmpeg", "m.mp4"]
    # ffmpeg takes the terminal's Ctrl-C too, and its close fails: the interrupt is still what
    # is raised (it read 'ffmpeg failed:', exit 2).
    _fake_ffmpeg(tmp_path, monkeypatch, 'for out; do :; done\ncat > "$out"\nexit 255')
    calls.clear()
    with pytest.raises(KeyboardInterrupt):
        render_usd(path, out, frames="all", width=W, height=H, supersample=1)
    assert out.read_bytes() == whole and sorted(os.listdir(tmp_path)) == ["anim.usdc", "ffmpeg", "m.mp4"]


@pytest.mark.parametrize("kind", ["dir", "png"])
def test_a_full_disk_under_the_pictures_is_exit_4_naming_the_file(tmp_path, monkeypatch, capsys, kind):
    """A picture that could not be written (a full disk) was exit 2, 'bad input', with the bare
    '[Errno 28] No space left on device'; now one line names it and what is written, exit 4."""
    import errno

    path = tmp_path / "anim.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=3)
    real, saves = Image.Image.save, []

    def full(self, fp, *args, **kwargs):
        saves.append(fp)
        if len(saves) == 2 or kind == "png":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(self, fp, *args, **kwargs)

    monkeypatch.setattr(Image.Image, "save", full)
    out = tmp_path / ("pictures" if kind == "dir" else "one.png")
    assert main(["render", str(path), "-o", str(out) + ("/" if kind == "dir" else ""), "--width", "32", "--height", "24"]) == 4
    err = capsys.readouterr().err
    if kind == "dir":
        assert err == (f"warp-esph: error: cannot write {out / 'frame_00001.png'}: No space left on device (1 of the 3 frames "
                       f"are written whole in {out}/)\n")
        assert os.listdir(out) == ["frame_00000.png"]
    else:
        assert err == (f"warp-esph: error: cannot write {out}: No space left on device (not written; a file of that name is "
                       "left as it was)\n")
        assert os.listdir(tmp_path) == ["anim.usdc"]


def test_an_interrupted_save_keeps_the_earlier_picture_and_leaves_no_part_file(tmp_path, monkeypatch):
    """Each picture is written beside its name and renamed over it: Ctrl-C inside a save left
    a truncated PNG, over the same frame of an earlier render too."""
    path = tmp_path / "anim.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=3)
    folder = tmp_path / "frames"
    render_usd(path, folder, width=W, height=H, supersample=1)
    before = {name: (folder / name).read_bytes() for name in os.listdir(folder)}
    real = Image.Image.save

    def interrupted(self, fp, *a, **k):
        if "frame_00001" in str(getattr(fp, "name", fp)):
            fp.write(b"\x89PNG\r\n")  # a few bytes, then Ctrl-C
            raise KeyboardInterrupt
        return real(self, fp, *a, **k)

    monkeypatch.setattr(Image.Image, "save", interrupted)
    with pytest.raises(KeyboardInterrupt):
        render_usd(path, folder, width=W, height=H, supersample=1, azimuth=90.0)
    assert sorted(os.listdir(folder)) == sorted(before)  # no working file left
    monkeypatch.setattr(Image.Image, "save", real)
    again = render_usd(path, tmp_path / "twice", frames="0,1", width=W, height=H, supersample=1)
    assert again.files == [str(tmp_path / "twice" / "frame_00000.png"), str(tmp_path / "twice" / "frame_00001.png")]
    monkeypatch.setattr(Image.Image, "save", interrupted)
    assert (folder / "frame_00001.png").read_bytes() == before["frame_00001.png"]
    assert (folder / "frame_00000.png").read_bytes() != before["frame_00000.png"]  # redrawn from another side
    with Image.open(folder / "frame_00001.png") as im:
        im.load()


def test_a_file_of_subframe_samples_or_no_rate_is_refused_not_misread(tmp_path):
    """Another program's samples between frames (0.5, 1.5) were rounded onto frames 0 and 2:
    render drew those frames twice and export wrote them once, the samples between never read.
    A time-code rate of 0 read as 30 fps, a negative one went into frames.pvd as negative times."""
    from pxr import Usd, UsdGeom

    from warp_esph.export import export_frames

    sub = tmp_path / "sub.usda"
    write_clusters(sub, [(0.0, 0.2, 0.0)], frames=3)
    stage = Usd.Stage.Open(str(sub))
    geom = UsdGeom.Points(next(p for p in stage.GetPrimAtPath("/World").GetChildren() if p.IsA(UsdGeom.Points)))
    geom.GetPointsAttr().Set(geom.GetPointsAttr().Get(Usd.TimeCode(1.0)), Usd.TimeCode(0.5))
    stage.GetRootLayer().Save()
    for rate in (0.0, -24.0):
        path = tmp_path / f"rate{rate:g}.usda"
        write_clusters(path, [(0.0, 0.2, 0.0)], frames=2)
        stage = Usd.Stage.Open(str(path))
        stage.SetTimeCodesPerSecond(rate)
        stage.GetRootLayer().Save()
        for call in (lambda: render_usd(path, tmp_path / "r.gif", width=W, height=H),
                     lambda: export_frames(path, "vtu", tmp_path / "r_vtu")):
            with pytest.raises(ValueError, match=f"cannot read .*rate{rate:g}.usda.*: timeCodesPerSecond = {rate:g} is not "
                                                 "allowed: must be a finite number > 0"):
                call()
    for call in (lambda: render_usd(sub, tmp_path / "s.gif", width=W, height=H),
                 lambda: export_frames(sub, "vtu", tmp_path / "s_vtu")):
        with pytest.raises(ValueError, match=r"cannot read .*sub.usda.*: its points have time samples at time codes that "
                                             r"are not whole numbers \(0.5\)"):
            call()
    assert not (tmp_path / "s_vtu").exists() and not (tmp_path / "r_vtu").exists()


def test_a_damaged_suggested_view_is_named_by_the_file(tmp_path):
    """The file's warp_esph:view went to the camera unchecked: NaN failed as 'cannot convert float
    NaN to integer', text as float()'s message, inf as 'math domain error', none naming the file;
    an elevation of 90 (which --elevation refuses) was drawn looking along the up axis. The view
    is a hint: one that is no pair of finite degrees is left out with a warning naming the file,
    an elevation past 89 degrees (older writers took 90) is brought to 89, and the file is drawn."""
    from pxr import Sdf, Vt

    from warp_esph.usd import UsdFrames

    path = tmp_path / "v.usda"
    model = write_clusters(path, [(0.0, 0.2, 0.0)], frames=1)

    def with_view(view):
        layer = Sdf.Layer.FindOrOpen(str(path))
        layer.Reload(force=True)
        layer.customLayerData = {**dict(layer.customLayerData), "warp_esph:view": view}
        layer.Save()

    for view, shown in ((Vt.DoubleArray([np.nan, 20.0]), "[nan, 20.0]"), ("ab", "'ab'"), ("12", "'12'"),
                        (Vt.DoubleArray([np.inf, 1e300]), "[inf, 1e+300]")):
        with_view(view)
        with pytest.warns(UserWarning, match=rf"v.usda: its warp_esph:view = {re.escape(shown)} is no \(azimuth, "
                                              r"elevation\) in finite degrees; the suggested view is left out"):
            assert UsdFrames(path).view is None
        with pytest.warns(UserWarning):
            render_usd(path, tmp_path / "v.png", width=W, height=H)
    with_view(Vt.DoubleArray([30.0, 90.0]))
    assert UsdFrames(path).view == (30.0, 89.0)
    render_usd(path, tmp_path / "v.png", width=W, height=H)
    with pytest.raises(ValueError, match=r"view elevation = 90.0 is not allowed: must be in \[-89.0, 89.0\]"):
        we.UsdWriter(tmp_path / "w.usdc", model, 10.0, view=(30.0, 90.0))


def test_a_damaged_file_is_named_not_drawn_empty(tmp_path):
    """A frame whose every point is NaN rendered as an empty picture and exited 0, and a NaN
    width failed inside the renderer ('cannot convert float NaN to integer')."""
    from pxr import Usd, UsdGeom

    from warp_esph.export import export_frames

    for name, points, widths in (("nan_points", [(np.nan, 0.0, 0.0)] * 2, [0.02, 0.02]),
                                 ("bad_widths", [(0.0, 0.0, 0.0), (0.1, 0.0, 0.0)], [-1.0, np.nan])):
        path = tmp_path / f"{name}.usda"
        write_clusters(path, [(0.0, 0.2, 0.0)], frames=1)
        stage = Usd.Stage.Open(str(path))
        prim = next(p for p in stage.GetPrimAtPath("/World").GetChildren() if p.IsA(UsdGeom.Points))
        geom = UsdGeom.Points(prim)
        geom.GetPointsAttr().Set(points, Usd.TimeCode(0.0))
        geom.GetWidthsAttr().Set(widths, Usd.TimeCode(0.0))
        stage.GetRootLayer().Save()
        calls = [lambda: render_usd(path, tmp_path / f"{name}.png", width=W, height=H)]
        if name == "nan_points":  # export writes no widths, so bad ones are not its to refuse
            calls.append(lambda: export_frames(path, "vtu", tmp_path / f"{name}_vtu"))
        for call in calls:
            with pytest.raises(ValueError, match=f"cannot read .*{name}.usda.*: (frame 0 has no particle with a finite "
                                                 "position|body .* at frame 0 has widths that are not finite and > 0)"):
                call()
    with pytest.raises(ValueError, match="path = None is not allowed"):
        render_usd(None)
    with pytest.raises(ValueError, match="output = 123 is not allowed: must be a path"):
        render_usd(tmp_path / "nan_points.usda", 123)


def test_a_renderer_takes_its_frames_as_a_range_a_numpy_array_or_an_iterator(tmp_path):
    """``Renderer`` took ``frames`` by ``list(frames)``; then only by ``parse_frames``, which
    refused a range or a numpy array ('frames = range(0, 2) is not allowed'). Any iterable of
    frame numbers is taken again, and a frame the file lacks is still refused by name."""
    path = tmp_path / "three.usdc"
    write_clusters(path, [(0.0, 0.0, 0.0)], frames=3, shift=(0.1, 0.0, 0.0))
    data = UsdFrames(path)
    o = RenderOptions(width=W, height=H, supersample=1)
    assert Renderer(data, range(1, 3), o).frames == [1, 2]
    assert Renderer(data, np.array([0, 2]), o).frames == [0, 2]
    assert Renderer(data, iter([2]), o).frames == [2]
    with pytest.raises(ValueError, match=r"^frames = \[3\] is not allowed: frame 3 is not in the file \(it holds 0\.\.2\)$"):
        Renderer(data, np.arange(3, 4), o)


def test_a_ctrl_c_mid_render_says_which_pictures_are_kept_and_leaves_no_open_file(tmp_path, monkeypatch, capsys):
    """A Ctrl-C inside a PNG's encoding: PIL closes the file it opened only on an ``Exception``,
    so the working file was left to the garbage collector ('warning: unclosed file
    <.frame_00001.PID.part.png>'), and the one line said 'interrupted' and nothing of the
    pictures kept, where an interrupted run or export says what its files hold."""
    path = tmp_path / "anim.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=3)
    Image.init()
    real = Image.SAVE["PNG"]

    def interrupted(im, fp, filename):
        if "frame_00001" in str(filename):
            fp.write(b"\x89PNG\r\n")  # a few bytes, then Ctrl-C
            raise KeyboardInterrupt
        return real(im, fp, filename)

    monkeypatch.setitem(Image.SAVE, "PNG", interrupted)
    folder = tmp_path / "frames"
    size = ["--width", str(W), "--height", str(H), "--supersample", "1"]
    assert main(["render", str(path), "-o", str(folder), *size]) == 130
    assert capsys.readouterr().err == f"warp-esph: interrupted: 1 of the 3 frames are written whole in {folder}\n"
    assert sorted(os.listdir(folder)) == ["frame_00000.png"]
    with Image.open(folder / "frame_00000.png") as im:
        im.load()
    sheet = tmp_path / "sheet.png"
    monkeypatch.setitem(Image.SAVE, "PNG", lambda im, fp, filename: (_ for _ in ()).throw(KeyboardInterrupt))
    assert main(["render", str(path), "-o", str(sheet), "--frames", "all", *size]) == 130
    assert capsys.readouterr().err == (f"warp-esph: interrupted: {sheet} is not written (a file of that name is left "
                                       "as it was)\n")
    assert sorted(os.listdir(tmp_path)) == ["anim.usdc", "frames"]
    # From Python: exactly a KeyboardInterrupt, which Python alone ends a script on with the
    # SIGINT status (130); a subclass of it exited 1.
    with pytest.raises(KeyboardInterrupt) as stopped:
        render_usd(path, str(sheet), frames="all", width=W, height=H, supersample=1)
    assert type(stopped.value) is KeyboardInterrupt and stopped.value.kept == f"{sheet} is not written (a file of that name is left as it was)"
