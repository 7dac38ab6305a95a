"""The interactive viewer driven headless through scripted input (dmrt/app/viewer.py, dmrt/app/viewer_window.py).

No mocks: the real renderers on the tiny scene's bundle, at 160x107 pixels. Photo streaming is
synchronous and unbounded (``async_photos=False, max_uploads_per_frame=0``) so that a frame's
colours depend only on its camera: recorded paths then replay to the same images.
"""

import dataclasses
import json
import os
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from dmrt.io.bundle import read_bundle
from dmrt.app.cli import main
from dmrt.runtime.renderer import RenderConfig
from dmrt.io.frames import label_colors
from dmrt.app.viewer import Viewer, ViewerConfig

W, H = 160, 107
DETERMINISTIC = RenderConfig(async_photos=False, max_uploads_per_frame=0)


def make_viewer(bundle_path, tmp_path, render: RenderConfig = DETERMINISTIC, **kw) -> Viewer:
    config = ViewerConfig(width=W, height=H, layers=3, photo=1, overlay=False, max_renderers=2,
                          path_file=tmp_path / "path.json", screenshot_file=tmp_path / "shot.png", **kw)
    return Viewer(read_bundle(bundle_path), config, render)


def centre_depth(frame) -> float:
    """Median camera z of the 3x3 pixels at the frame's centre (the optical axis)."""
    return float(np.median(frame["depth"][H // 2 - 1:H // 2 + 2, W // 2 - 1:W // 2 + 2]))


@pytest.mark.e2e
def test_scripted_session(tiny_bundle, ctx, tmp_path):
    v = make_viewer(tiny_bundle, tmp_path)
    bundle = v.bundle
    start = v.render()
    # the colour buffer is displayed texel for texel at the frame's size
    assert start.shape == (H, W, 3) and np.array_equal(start, v.frame["color"])
    assert np.allclose(v.camera.center, bundle.cameras[1].center)
    z0 = centre_depth(v.frame)
    assert z0 > 0

    # fly forward for half a second: the camera moves along its view axis by speed * 0.5, so the
    # surface point on the optical axis comes that much closer (its depth is raytraced to well
    # under a centimetre; 3 cm allows for the 3x3 median over a slanted surface)
    forward, before = v.R[2].copy(), v.position.copy()
    v.key("w")
    v.step(0.5)
    v.key("w", pressed=False)
    v.step(0.5)  # released: no further motion
    moved = 0.5 * v.speed
    assert np.allclose(v.position - before, moved * forward)
    img = v.render()
    assert np.mean(np.any(img != start, axis=-1)) > 0.3
    assert abs((z0 - centre_depth(v.frame)) - moved) < 0.03

    # turn right by dragging 50 px (10 degrees): the point on the old optical axis moves left of
    # the centre by about f tan(10 deg) (exactly so for a level camera; the yaw is about the world
    # up and the photo looks slightly down: 1.5 px), and the new frame sees it there at its depth
    point = v.camera.center + centre_depth(v.frame) * forward
    right, up = v.R[0].copy(), v.up
    v.drag(50, 0)
    assert v.R[2] @ right > 0 and abs(v.R[0] @ up - right @ up) < 1e-6  # turned right, horizon kept
    v.render()
    cam = v.camera
    uv, z = cam.project(point[None])
    expect_u = W / 2 - cam.fx * np.tan(np.radians(50 * v.config.drag_degrees))
    assert abs(uv[0, 0] - expect_u) < 1.5 and abs(uv[0, 1] - H / 2) < 2.0
    i, j = int(uv[0, 1]), int(uv[0, 0])
    assert abs(float(np.median(v.frame["depth"][i - 1:i + 2, j - 1:j + 2])) - z[0]) < 0.03

    # buffers: labels and splat labels map one-to-one to colours (the numpy mirror of the shader)
    v.key("b")
    assert v.buffer == "depth"
    depth_img = v.render()
    z = v.frame["depth"]
    grey = depth_img[..., 0].astype(float)
    assert np.all(depth_img[..., 0] == depth_img[..., 2]) and np.all(grey[z == 0] == 0)
    assert np.corrcoef(z[z > 0], grey[z > 0])[0, 1] < -0.95  # near bright, far dim
    for name, key in (("label", "label"), ("splat_label", "splat_label")):
        v.set_buffer(name)
        img = v.render()
        labels = v.frame[key]
        assert np.abs(img.astype(int) - label_colors(labels)).max() <= 1
        pairs = np.unique(np.concatenate([labels.reshape(-1, 1), img.reshape(-1, 3)], axis=1), axis=0)
        assert len(pairs) == len(np.unique(labels)) == len(np.unique(img.reshape(-1, 3), axis=0)) >= 3
    assert np.array_equal(v.frame["splat_label"], v.renderer().layers()["label"][0])
    v.set_buffer("holes")
    img = v.render()
    holes = v.frame["layer_used"] < 0
    assert 0 < holes.mean() < 0.5
    assert np.array_equal(np.all(img == (255, 0, 0), axis=-1), holes)
    v.set_buffer("iterations")
    img = v.render()
    it = v.frame["iterations"]
    assert img[it == it.max()].min() == 255 and np.all(img[it == 0] == 0)

    # method: coarse splats differ from DMRT at the same view; layer count: a new renderer
    v.set_buffer("color")
    dmrt_img = v.render()
    v.key("m")
    assert v.method == "splats"
    splats_img = v.render()
    assert np.mean(np.any(splats_img != dmrt_img, axis=-1)) > 0.1
    while v.method != "dmrt":
        v.key("m")
    v.key("]")
    assert v.layers == 4 and v.renderer().config.layers == 4
    assert len(v._renderers) <= v.config.max_renderers  # least recently used one released

    # photo cameras: number keys and page down / up
    v.key("5")
    assert v.photo == 4 and np.allclose(v.camera.center, bundle.cameras[4].center)
    assert np.allclose(v.R, bundle.cameras[4].R)
    v.key("page_down")
    v.key("page_up")
    assert v.photo == 4
    at_photo = v.render()
    assert np.mean(np.any(at_photo != dmrt_img, axis=-1)) > 0.3

    # record three frames while strafing right, then replay the path with `dmrt render`
    v.key("r")
    recorded = []
    v.key("d")
    for _ in range(3):
        v.step(0.2)
        recorded.append(v.render())
    v.key("d", pressed=False)
    v.key("r")
    assert v.last_path == tmp_path / "path.json"
    assert len(json.loads(v.last_path.read_text())["cameras"]) == 3
    out = tmp_path / "replay"
    assert main(["render", str(tiny_bundle), "--path", str(v.last_path), "--out", str(out), "--layers", "4",
                 "--no-async-photos", "--max-uploads-per-frame", "0"]) == 0
    replayed = [np.asarray(Image.open(p).convert("RGB")) for p in sorted(out.glob("frame_*.png"))]
    assert len(replayed) == 3 and not np.array_equal(recorded[0], recorded[2])
    # same renderer, same cameras (JSON keeps float64 exactly), every photo resident: identical
    for a, b in zip(recorded, replayed):
        assert np.array_equal(a, b)

    # screenshot (F12) and the overlay
    v.key("f12")
    assert v.last_screenshot == tmp_path / "shot.png"
    assert np.array_equal(np.asarray(Image.open(v.last_screenshot).convert("RGB")), v.image())
    plain = v.image()
    v.key("h")
    v.update()
    with_overlay = v.image()
    changed = np.any(with_overlay != plain, axis=-1)
    assert changed[:H // 3].mean() > 0.05 and not changed[-H // 4:].any()  # a box at the top only
    if v.methods["dmrt"].uses_leveling:
        v.key("l")
        assert v.leveling and v.renderer().config.leveling
    v.close()


def test_orbit(tiny_bundle, ctx, tmp_path):
    """``o`` orbits around the surface point at the image centre: dragging and the arrow keys move
    the camera on a sphere around it (the point stays at the image centre, at the same distance,
    and the frame still sees the surface there), w comes closer without passing it; ``o`` again
    flies."""
    v = make_viewer(tiny_bundle, tmp_path)
    v.render()
    z0 = centre_depth(v.frame)
    v.key("o")
    pivot = v.pivot.copy()
    assert np.allclose(pivot, v.position + v.frame["depth"][H // 2, W // 2] * v.R[2])
    start = v.position.copy()
    v.drag(60, -20)
    v.key("right")
    v.step(0.5)
    v.key("right", pressed=False)
    assert np.linalg.norm(v.position - start) > 0.1 * z0  # the camera moved around
    assert abs(np.linalg.norm(v.position - pivot) - np.linalg.norm(start - pivot)) < 1e-9
    uv, z = v.camera.project(pivot[None])
    assert np.allclose(uv[0], (W / 2, H / 2), atol=1e-6)
    v.render()
    # the surface point is still on the optical axis (3x3 median; 5 cm: a slanted surface)
    assert abs(centre_depth(v.frame) - z[0]) < 0.05
    d0 = np.linalg.norm(v.position - pivot)
    v.key("w")
    v.step(100.0)  # far more than the distance: stops short of the pivot
    v.key("w", pressed=False)
    assert 0 < np.linalg.norm(v.position - pivot) < d0
    v.key("o")
    assert v.pivot is None
    v.close()


def test_window_app_headless(tiny_bundle, ctx, tmp_path):
    """The moderngl-window path: a headless window on the shared context, events forwarded."""
    from dmrt.app.viewer_window import create_app, run_app

    config = ViewerConfig(width=W, height=H, layers=2, overlay=False, path_file=tmp_path / "p.json")
    app = create_app(read_bundle(tiny_bundle), config, DETERMINISTIC, window="headless")
    v, wnd = app.viewer, app.wnd
    assert wnd.ctx is ctx and (v.width, v.height) == (W, H)
    R, fov = v.R.copy(), v.fov
    app.on_mouse_drag_event(0, 0, 20, 5)
    app.on_mouse_scroll_event(0.0, 2.0)
    assert not np.allclose(v.R, R) and v.fov < fov
    wnd.render(0.0, 0.1)  # one frame through on_render into the window's framebuffer
    shown = np.flipud(np.frombuffer(wnd.fbo.read(components=3), np.uint8).reshape(H, W, 3))
    assert "color" not in v.frame  # the window's frames stay on the GPU
    assert np.array_equal(shown, v.image())
    v.update(record=False)  # the same view read back: the same colours
    assert np.array_equal(shown, v.frame["color"])
    v.key("r")
    run_app(app, frames=2, screenshot=tmp_path / "still.png")
    assert wnd.frames >= 2
    assert np.asarray(Image.open(tmp_path / "still.png")).shape == (H, W, 3)
    # closing wrote the recording in progress: the two frames of the loop
    assert len(json.loads((tmp_path / "p.json").read_text())["cameras"]) == 2


@pytest.mark.e2e
def test_view_command(tiny_bundle, ctx, tmp_path, capsys, monkeypatch):
    still = tmp_path / "view.png"
    assert main(["view", str(tiny_bundle), "--window", "headless", "--frames", "2", "--width", "96",
                 "--height", "64", "--layers", "2", "--buffer", "label", "--screenshot", str(still)]) == 0
    assert np.asarray(Image.open(still)).shape == (64, 96, 3)
    # no display: one clear line, how to run headless, exit status 2, no traceback
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert main(["view", str(tiny_bundle)]) == 2
    err = capsys.readouterr().err
    assert "cannot open a window: no display" in err and "--window headless" in err
    assert "Traceback" not in err
    with pytest.raises(SystemExit) as exit_info:  # argparse knows the choices (ViewerConfig.buffer's Literal)
        main(["view", str(tiny_bundle), "--buffer", "nope"])
    assert exit_info.value.code == 2
    assert "--buffer: invalid choice: 'nope' (choose from" in capsys.readouterr().err


PYGLET_SCRIPT = """
import json, sys
from dmrt.io.bundle import read_bundle
from dmrt.runtime.renderer import RenderConfig
from dmrt.app.viewer import ViewerConfig
from dmrt.app.viewer_window import create_app, run_app
from pyglet.window import key

app = create_app(read_bundle(sys.argv[1]), ViewerConfig(width=96, height=64, layers=2, overlay=False),
                 RenderConfig(async_photos=False, max_uploads_per_frame=0), window="pyglet")
v, win = app.viewer, app.wnd._window
win._enable_event_queue = False  # deliver the synthetic events at once
start = v.position.copy()
win.dispatch_event("on_key_press", key.W, 0)
app.wnd.render(0.0, 0.5)  # half a second with W held
win.dispatch_event("on_key_release", key.W, 0)
moved = float(((v.position - start) ** 2).sum() ** 0.5 / v.speed)
for k in (key.B, key.BRACERIGHT, key._3):
    win.dispatch_event("on_key_press", k, 0)
    win.dispatch_event("on_key_release", k, 0)
run_app(app, frames=2)
print(json.dumps({"moved": moved, "buffer": v.buffer, "layers": v.layers, "photo": v.photo}))
"""


@pytest.fixture(scope="module")
def display():
    """The session's X display, else a virtual one (Xvfb, which setup.sh installs)."""
    import shutil
    import time

    if os.environ.get("DISPLAY"):
        yield os.environ["DISPLAY"]
        return
    if shutil.which("Xvfb") is None:
        pytest.fail("no display and no Xvfb: install xvfb (setup.sh does) to test the viewer's window")
    name = f":{90 + os.getpid() % 500}"
    server = subprocess.Popen(["Xvfb", name, "-screen", "0", "640x480x24", "-nolisten", "tcp"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        for _ in range(100):  # the server is up when its socket exists
            if os.path.exists(f"/tmp/.X11-unix/X{name[1:]}"):
                break
            time.sleep(0.05)
        yield name
    finally:
        server.terminate()
        server.wait()


@pytest.mark.e2e
def test_pyglet_window_keys(tiny_bundle, display):
    """A real window (on a virtual X display without one): pyglet's key codes reach the viewer. In
    its own process: the window's GL context would otherwise become current in place of the tests'
    one."""
    run = subprocess.run([sys.executable, "-c", PYGLET_SCRIPT, str(tiny_bundle)], capture_output=True, text=True,
                         timeout=300, env={**os.environ, "DISPLAY": display})
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout.strip().splitlines()[-1])
    assert abs(out["moved"] - 0.5) < 1e-6 and out == {**out, "buffer": "depth", "layers": 3, "photo": 2}


@pytest.mark.e2e
def test_proxy_set_switch(tiny_scene, ctx, tmp_path):
    """``p`` switches the proxy set between the k coarsest octree levels of a bundle preprocessed
    with two: the coarser set is the first level's points (their labels kept, radii from their
    own, sparser density: larger), the frame changes, and ``p`` again returns to both levels."""
    from dmrt.preprocess.pipeline import PreprocessConfig, preprocess

    path = preprocess(tiny_scene, tmp_path / "two-levels", PreprocessConfig(depthmap_width=128, proxy_levels=2),
                      progress=False)
    # the fixed labels: the proxies' labels texture the frame, so their set shows in its colours
    v = make_viewer(path, tmp_path, dataclasses.replace(DETERMINISTIC, photo_choice="labels"))
    full = v.bundle.proxy
    assert v.max_proxy_levels == v.proxy_levels == 2
    fine = v.render().copy()
    v.key("p")
    assert v.proxy_levels == 1
    coarse = v.proxy_bundle().proxy
    n = v.bundle.meta["counts"]["octree_level_counts"][0]
    assert len(coarse["positions"]) == n < len(full["positions"])
    np.testing.assert_array_equal(coarse["labels"], full["labels"][:n])
    assert np.median(coarse["radii"] / full["radii"][:n]) > 1.2
    assert v.renderer().splats.n == int((coarse["labels"] >= 0).sum())
    assert np.mean(np.any(v.render() != fine, axis=-1)) > 0.01
    v.key("p")
    assert v.proxy_levels == 2 and v.renderer().splats.n == int((full["labels"] >= 0).sum())
    v.close()


@pytest.mark.parametrize("method", ["dmrt", "dmt"])
def test_live_frames_show_what_read_back_frames_show(tiny_bundle, ctx, tmp_path, method):
    """``update(readback=False)``: the colour view copies the renderer's colours into the display
    on the GPU and reads nothing back; the image equals the one of the same frame read back. The
    orbit's pivot reads the centre pixel's depth alone; other views still read the frame back."""
    v = make_viewer(tiny_bundle, tmp_path, method=method)
    try:
        live = v.update(readback=False)
        assert "color" not in live and "depth" not in live and live["timings"]
        shown = v.image()
        v.update()
        assert np.array_equal(shown, v.image()) and np.array_equal(shown, v.frame["color"])
        v.update(readback=False)
        v.toggle_orbit()  # the centre pixel's depth, read from the frame on the GPU
        assert "depth" not in v.frame
        v.update()  # the same view, read back
        z = float(v.frame["depth"][H // 2, W // 2])
        assert z > 0 and np.allclose(v.pivot, v.position + z * v.R[2])
        v.set_buffer("depth")
        assert "depth" in v.update(readback=False)  # a view other than the colour: read back
    finally:
        v.close()
