"""The viewer's window (``dmrt view``): moderngl-window forwards keys, mouse and resizes to a
:class:`dmrt.app.viewer.Viewer` and shows its frames.

Window backends are moderngl-window's: ``pyglet`` (default, installed with it), ``glfw`` /
``sdl2`` / ``pyside2`` (``pip install`` the package of that name), and ``headless`` - an off-screen
framebuffer on the process's EGL context (:func:`dmrt.gl.get_context`), which runs the same main
loop without a display (tests; ``--frames N --screenshot FILE`` for a still). When no window can
be opened, :class:`NoDisplayError` says what is missing and how to run headless.
"""

from __future__ import annotations

import os
import warnings

with warnings.catch_warnings():  # moderngl-window 3.1 imports PyGLM by its soon-deprecated name
    warnings.simplefilter("ignore", PendingDeprecationWarning)
    import moderngl_window as mglw
    from moderngl_window.context.headless import Window as HeadlessWindow
    from moderngl_window.timers.clock import Timer

from dmrt.errors import InputError
from dmrt.gl.context import get_context
from dmrt.app.viewer import Viewer

# moderngl-window key constants (BaseKeys attribute names) -> Viewer.key names
KEY_NAMES = {
    **{c: c.lower() for c in "WASDQEMBLRH"},
    **{f"NUMBER_{i}": str(i) for i in range(10)},
    "LEFT": "left", "RIGHT": "right", "UP": "up", "DOWN": "down",
    "PAGE_UP": "page_up", "PAGE_DOWN": "page_down",
    "LEFT_BRACKET": "[", "RIGHT_BRACKET": "]", "EQUAL": "+", "MINUS": "-", "F12": "f12",
    "LEFT_SHIFT": "shift", "RIGHT_SHIFT": "shift",
}


class NoDisplayError(InputError):
    """No window could be opened; the message names what is missing and the headless commands.
    An :class:`InputError`, so ``dmrt`` prints it on one line and exits with status 2."""

    def __init__(self, message: str):
        super().__init__(None, message)


class SharedContextHeadlessWindow(HeadlessWindow):
    """moderngl-window's headless window on the process's shared EGL context.

    The suite runs all GL in one context per process (DESIGN.md, :mod:`dmrt.gl.context`):
    moderngl objects belong to the context that made them and moderngl does not switch the
    current context per call, so a second context would take GL calls meant for the first.
    """

    def init_mgl_context(self) -> None:
        self._ctx = get_context(self.gl_version_code)
        self._create_fbo()
        self.use()

    def destroy(self) -> None:
        """Free the window's framebuffer; the shared context outlives the window."""
        if self._ctx.fbo is self._fbo:  # see Viewer.image: never leave a released framebuffer bound
            self._ctx.detect_framebuffer(0).use()
        for tex in [*self._fbo.color_attachments, self._fbo.depth_attachment]:
            if tex is not None:
                tex.release()
        self._fbo.release()
        self._fbo = None


class ViewerApp(mglw.WindowConfig):
    """Forwards a window's events to a :class:`Viewer` and draws its frame every frame.

    Built by :func:`create_app`; ``wnd`` and ``ctx`` are the window and its context, ``viewer``
    the Viewer rendering on that context.
    """

    gl_version = (4, 3)  # compute shaders (the renderers' stages)
    title = "dmrt view"

    def __init__(self, viewer: Viewer, **kwargs):
        super().__init__(**kwargs)
        self.viewer = viewer
        keys = self.wnd.keys
        # the headless window has no key codes ("undefined"): it gets no key events anyway
        self.key_names = {getattr(keys, const): name for const, name in KEY_NAMES.items()
                          if getattr(keys, const, "undefined") != "undefined"}
        self._title_time = -1.0

    def on_render(self, time: float, frame_time: float) -> None:
        self.viewer.step(frame_time)
        self.viewer.update(readback=False)  # the colour view stays on the GPU
        self.viewer.draw(self.wnd.fbo, self.wnd.viewport)
        if time - self._title_time > 0.5:  # the title is the overlay's first line, twice a second
            self.wnd.title = f"dmrt view - {self.viewer.status()[0]}"
            self._title_time = time

    def on_key_event(self, key, action, modifiers) -> None:
        name = self.key_names.get(key)
        if name is not None:
            self.viewer.key(name, pressed=action == self.wnd.keys.ACTION_PRESS)

    def on_mouse_drag_event(self, x: int, y: int, dx: int, dy: int) -> None:
        self.viewer.drag(dx, dy)

    def on_mouse_scroll_event(self, x_offset: float, y_offset: float) -> None:
        self.viewer.scroll(y_offset)

    def on_resize(self, width: int, height: int) -> None:
        self.viewer.resize(*self.wnd.buffer_size)


def _no_display_message(window: str, exc: Exception) -> str:
    if isinstance(exc, ImportError) and window != "pyglet":  # pyglet comes with moderngl-window
        what = f"the '{window}' window backend is not installed (pip install {window})"
    elif window != "headless" and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        what = "no display (neither DISPLAY nor WAYLAND_DISPLAY is set)"
    else:
        what = f"the '{window}' window failed to open"
    return (f"cannot open a window: {what}; {type(exc).__name__}: {exc}. "
            f"Run it in a desktop session (or over ssh -X), or without a window: "
            f"'dmrt view BUNDLE --window headless --frames 10 --screenshot view.png' renders 10 frames "
            f"and saves a still; 'dmrt path BUNDLE --out path.json' then "
            f"'dmrt render BUNDLE --path path.json --out DIR' renders a walkthrough.")


def open_window(width: int, height: int, window: str = "pyglet"):
    """A moderngl-window window with a GL 4.3 context (``headless``: on the shared EGL context).

    Raises
    ------
    NoDisplayError
        When the backend is not installed or cannot open a window (no display, no GL 4.3).
    """
    try:
        cls = SharedContextHeadlessWindow if window == "headless" else mglw.get_local_window_cls(window)
        wnd = cls(title=ViewerApp.title, size=(width, height), gl_version=ViewerApp.gl_version, resizable=True,
                  vsync=False, cursor=True)
    except Exception as exc:  # backends raise their own types (pyglet: NoSuchDisplayException)
        raise NoDisplayError(_no_display_message(window, exc)) from exc
    mglw.activate_context(window=wnd)
    return wnd


def create_app(bundle, config=None, render_config=None, window: str = "pyglet") -> ViewerApp:
    """Open a window and a :class:`Viewer` of ``bundle`` rendering on its context."""
    from dmrt.app.viewer import ViewerConfig

    config = config or ViewerConfig()
    wnd = open_window(config.width, config.height, window)
    viewer = Viewer(bundle, config, render_config, ctx=wnd.ctx)
    viewer.resize(*wnd.buffer_size)  # a HiDPI window has more pixels than its size
    app = ViewerApp(viewer, ctx=wnd.ctx, wnd=wnd, timer=Timer())
    wnd.swap_buffers()  # as moderngl-window does: may deliver the window's real size first
    wnd.set_default_viewport()
    return app


def run_app(app: ViewerApp, frames: int | None = None, screenshot=None) -> None:
    """The main loop (moderngl-window's, which cannot be given this window class): until the
    window closes (Esc) or ``frames`` frames were shown; then save a still to ``screenshot``,
    write a recording in progress and close the window."""
    wnd, timer = app.wnd, app.timer
    timer.start()
    shown = 0
    try:
        while not wnd.is_closing and (frames is None or shown < frames):
            now, dt = timer.next_frame()
            wnd.use()
            wnd.render(now, dt)
            if not wnd.is_closing:
                wnd.swap_buffers()
            shown += 1
        if screenshot is not None:
            app.viewer.screenshot(screenshot)
    finally:
        timer.stop()
        app.viewer.close()
        wnd.destroy()


def run_viewer(bundle, config=None, render_config=None, window: str = "pyglet", frames: int | None = None,
               screenshot=None) -> None:
    """``dmrt view``: open the window and run until it closes (see :func:`run_app`)."""
    run_app(create_app(bundle, config, render_config, window), frames, screenshot)
