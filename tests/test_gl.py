"""GL plumbing on a real context: context info, the program loader, GPU timer queries."""

import moderngl
import numpy as np
import pytest

import dmrt.gl.shaders as shader_mod
from dmrt.gl import GpuTimer, ShaderError, get_context, load_program, renderer_info


def test_context_is_shared_and_described(ctx):
    assert get_context() is ctx
    info = renderer_info(ctx)
    assert info["renderer"] and info["vendor"] and info["version"]
    assert isinstance(info["is_software"], bool)
    assert ctx.version_code >= 430


@pytest.fixture
def shader_dir(tmp_path, monkeypatch):
    """Point the loader at a scratch shader folder (the real GL compiler still compiles them)."""
    monkeypatch.setattr(shader_mod, "SHADER_DIR", tmp_path)
    return tmp_path


def _write(folder, name, text):
    (folder / name).write_text(text)


def test_include_once_and_defines(ctx, shader_dir):
    # lib.glsl is reached twice (directly and through mid.glsl): a second copy would redefine
    # twice() and fail to compile, so a successful compile shows include-once protection
    _write(shader_dir, "lib.glsl", "float twice(float x) { return 2.0 * x; }\n")
    _write(shader_dir, "mid.glsl", '#include "lib.glsl"\nfloat quad(float x) { return twice(twice(x)); }\n')
    _write(shader_dir, "prog.glsl", """
#include "lib.glsl"
#include "mid.glsl"
#if defined COMPUTE_SHADER
layout(local_size_x = 1) in;
layout(std430, binding = 0) buffer Out { float o[]; };
void main() {
    o[0] = twice(VALUE);
    o[1] = quad(SMALL);
    o[2] = float(FLAG);
    o[3] = float(COUNT);
}
#endif
""")
    cs = load_program(ctx, "prog", {"VALUE": 3.5, "SMALL": 1e-5, "FLAG": True, "COUNT": 7})
    assert isinstance(cs, moderngl.ComputeShader)
    buf = ctx.buffer(reserve=16)
    buf.bind_to_storage_buffer(0)
    cs.run(1)
    ctx.memory_barrier()
    out = np.frombuffer(buf.read(), np.float32)
    np.testing.assert_allclose(out, [7.0, 4e-5, 1.0, 7.0], rtol=1e-6)
    buf.release()
    # cached per (ctx, name, defines)
    assert load_program(ctx, "prog", {"VALUE": 3.5, "SMALL": 1e-5, "FLAG": True, "COUNT": 7}) is cs
    assert load_program(ctx, "prog", {"VALUE": 1.0, "SMALL": 1e-5, "FLAG": True, "COUNT": 7}) is not cs


def test_stage_split_vertex_geometry_fragment(ctx, shader_dir):
    # one file, three stages; a comment naming COMPUTE_SHADER must not make it a compute program
    _write(shader_dir, "tri.glsl", """
// not a COMPUTE_SHADER
#if defined VERTEX_SHADER
in vec2 in_pos;
void main() { gl_Position = vec4(in_pos, 0.0, 1.0); }
#elif defined GEOMETRY_SHADER
layout(triangles) in;
layout(triangle_strip, max_vertices = 3) out;
void main() {
    for (int i = 0; i < 3; ++i) { gl_Position = gl_in[i].gl_Position; EmitVertex(); }
    EndPrimitive();
}
#elif defined FRAGMENT_SHADER
layout(location = 0) out float out_v;
void main() { out_v = VALUE; }
#endif
""")
    assert set(shader_mod.stage_sources("tri", {"VALUE": 2.0})) == {
        "VERTEX_SHADER", "GEOMETRY_SHADER", "FRAGMENT_SHADER"}
    prog = load_program(ctx, "tri", {"VALUE": 2.5})
    assert isinstance(prog, moderngl.Program)
    tex = ctx.texture((4, 4), 1, dtype="f4")
    fbo = ctx.framebuffer([tex])
    vbo = ctx.buffer(np.array([[-1, -1], [3, -1], [-1, 3]], np.float32))
    vao = ctx.vertex_array(prog, [(vbo, "2f", "in_pos")])
    with ctx.scope(fbo):  # restores the bound framebuffer: releasing a bound one breaks later binds
        fbo.clear()
        vao.render(moderngl.TRIANGLES)
    assert np.all(np.frombuffer(tex.read(), np.float32) == 2.5)
    for obj in (vao, vbo, fbo, tex):
        obj.release()


def test_compile_error_names_the_file(ctx, shader_dir):
    _write(shader_dir, "broken_lib.glsl", "float f() { return undefined_symbol; }\n")
    _write(shader_dir, "broken.glsl", '#include "broken_lib.glsl"\n'
           "#if defined COMPUTE_SHADER\nlayout(local_size_x = 1) in;\nvoid main() { f(); }\n#endif\n")
    with pytest.raises(ShaderError) as err:
        load_program(ctx, "broken")
    msg = str(err.value)
    assert str(shader_dir / "broken.glsl") in msg and "broken_lib.glsl" in msg
    assert "undefined_symbol" in msg  # the driver's log is kept


def test_missing_include_names_the_includer(ctx, shader_dir):
    _write(shader_dir, "orphan.glsl", '\n#include "nowhere.glsl"\n')
    with pytest.raises(ShaderError, match=r"nowhere\.glsl.*orphan\.glsl:2"):
        load_program(ctx, "orphan")
    _write(shader_dir, "nostage.glsl", "void main() {}\n")
    with pytest.raises(ShaderError, match=r"nostage\.glsl.*VERTEX_SHADER"):
        load_program(ctx, "nostage")


def test_project_shaders_compile(ctx):
    for name in ("splat_depth_compute", "splat_depth_compute_large", "fill_u32"):
        assert isinstance(load_program(ctx, name), moderngl.ComputeShader)
    for name in ("splat_depth_raster", "splat_depth_raster_large"):
        assert isinstance(load_program(ctx, name), moderngl.Program)


def _time_or_unavailable(ms: float, wall_ms: float) -> bool:
    """A timer value is NaN (not measured) or a time the GPU can have taken: >= 0 and no longer
    than the wall clock around it (1% and 0.1 ms of slack, as dmrt.gl.timer allows)."""
    return bool(np.isnan(ms) or 0 <= ms <= 1.01 * wall_ms + 0.1)


def test_timer_measures_draw_and_dispatch(ctx, shader_dir):
    import time

    t_start = time.perf_counter()
    _write(shader_dir, "t_cs.glsl", "#if defined COMPUTE_SHADER\nlayout(local_size_x = 64) in;\n"
           "layout(std430, binding = 0) buffer B { float b[]; };\n"
           "void main() { b[gl_GlobalInvocationID.x] = sqrt(float(gl_GlobalInvocationID.x)); }\n#endif\n")
    _write(shader_dir, "t_fs.glsl", "#if defined VERTEX_SHADER\nin vec2 in_pos;\n"
           "void main() { gl_Position = vec4(in_pos, 0.0, 1.0); }\n#elif defined FRAGMENT_SHADER\n"
           "layout(location = 0) out vec4 c;\nvoid main() { c = vec4(gl_FragCoord.x); }\n#endif\n")
    timer = GpuTimer(ctx)
    software = not timer.reliable
    buf = ctx.buffer(reserve=64 * 64 * 4)
    buf.bind_to_storage_buffer(0)
    fbo = ctx.simple_framebuffer((512, 512))
    prog = load_program(ctx, "t_fs")
    vbo = ctx.buffer(np.array([[-1, -1], [3, -1], [-1, 3]], np.float32))
    vao = ctx.vertex_array(prog, [(vbo, "2f", "in_pos")])

    def frame(reliable: bool) -> dict:
        timer.reset()
        timer.reliable = reliable
        with timer.section("dispatch"):
            load_program(ctx, "t_cs").run(64)
        with ctx.scope(fbo):
            for _ in range(2):  # a full-screen 512 x 512 draw gives every rasterizer thread tiles
                with timer.section("draw"):
                    vao.render(moderngl.TRIANGLES)
        return timer.ms

    # a software rasterizer measures nothing (llvmpipe: compute as 1 ns, draws as garbage up to
    # 448 s): every time is unavailable; a GPU's are times
    ms = frame(timer.reliable)
    assert set(ms) == {"dispatch", "draw"} and timer.counts == {"dispatch": 1, "draw": 2}
    assert all(np.isnan(v) == software for v in ms.values()), ms
    # read as a GPU's (llvmpipe's garbage too): each value is a possible time or unavailable, never
    # the 32-bit saturated 4294.97 ms nor more than the wall clock since the test began
    ms = frame(True)
    wall = (time.perf_counter() - t_start) * 1e3
    assert all(_time_or_unavailable(v, wall) for v in ms.values()), (ms, wall)
    timer.reliable = not software
    with pytest.raises(RuntimeError, match="nest"):
        with timer.section("outer"):
            with timer.section("inner"):
                pass
    # parts of a stage ("stage:part") add up to the stage and stay apart in part_ms
    timer.reset()
    with ctx.scope(fbo):
        for part in ("a", "b"):
            with timer.section(f"draw:{part}"):
                vao.render(moderngl.TRIANGLES)
    parts = timer.part_ms
    assert set(parts) == {"draw:a", "draw:b"}
    np.testing.assert_equal(timer.ms, {"draw": parts["draw:a"] + parts["draw:b"]})  # NaN == NaN here
    # fenced sections (glFinish around each) time the same work, one use each
    timer.reset()
    timer.fenced = True
    with ctx.scope(fbo):
        with timer.section("draw"):
            vao.render(moderngl.TRIANGLES)
    timer.fenced = False
    assert timer.counts == {"draw": 1} and set(timer.ms) == {"draw"} and timer.lag == 0
    timer.reset()
    assert timer.ms == {}
    # deferred: nothing read per frame, every frame's sections read at the end, in order
    timer.deferred = True
    with ctx.scope(fbo):
        for uses in (1, 2):
            for _ in range(uses):
                with timer.section("draw:a"):
                    vao.render(moderngl.TRIANGLES)
            with timer.section("draw:b"):
                vao.render(moderngl.TRIANGLES)
            assert timer.ms == {} and timer.lag is None
            timer.reset()
    frames = timer.collect()
    timer.deferred = False
    wall = (time.perf_counter() - t_start) * 1e3
    assert [set(f) for f in frames] == [{"draw:a", "draw:b"}] * 2
    assert all(_time_or_unavailable(v, wall) for f in frames for v in f.values())
    assert all(np.isnan(v) for f in frames for v in f.values()) or not software
    assert timer.collect() == [] and timer.ms == {}
    timer.release()
    for obj in (vao, vbo, fbo, buf):
        obj.release()


def test_timer_without_waiting_reads_earlier_frames(ctx):
    """``wait=False`` (the renderers' timers) never waits: a frame's times are those of the newest
    earlier frame the GPU has answered, ``lag`` frames back; ``wait=True`` reads the frame's own."""
    import time

    prog = ctx.program(vertex_shader="#version 430\nin vec2 in_pos;\nvoid main() { gl_Position = vec4(in_pos, 0, 1); }",
                       fragment_shader="#version 430\nuniform int u_n;\nout vec4 c;\nvoid main() {\n"
                       "  float a = gl_FragCoord.x;\n  for (int i = 0; i < u_n; ++i) a = sin(a) + 1.0001;\n"
                       "  c = vec4(a);\n}")
    vbo = ctx.buffer(np.array([[-1, -1], [3, -1], [-1, 3]], np.float32))
    vao = ctx.vertex_array(prog, [(vbo, "2f", "in_pos")])
    fbo = ctx.simple_framebuffer((128, 128))
    timer = GpuTimer(ctx, wait=False)

    def frame(name: str, loops: int) -> None:
        prog["u_n"].value = loops
        with ctx.scope(fbo), timer.section(name):
            vao.render(moderngl.TRIANGLES)

    frame("warm", 1)  # compiles the draw
    ctx.finish()
    timer.reset()
    # frame 1 draws for ~0.3 s on llvmpipe (far less on a GPU, still longer than the reads below)
    frame("slow", 2000)
    assert set(timer.ms) == {"warm"} and timer.lag == 1 and timer.frame == 1  # frame 0's, not its own
    f = timer.frame_timings(("slow", "warm", "leveling"))  # stages frame 0 did not time: 0
    assert f["timings_lag"] == 1 and f["timings"]["slow"] == f["timings"]["leveling"] == 0.0
    timer.reset()
    t0 = time.perf_counter()
    frame("next", 1)
    # frame 1 is still running: frame 2 reads frame 0's times (2 back) without waiting for it
    assert set(timer.ms) == {"warm"} and timer.lag == 2
    assert time.perf_counter() - t0 < 0.1  # a wait would have taken the slow draw's ~0.3 s
    ctx.finish()
    assert set(timer.ms) == {"slow"} and timer.lag == 1  # answered now; frame 2's own never read
    # a frame with nothing answered before it: its timed stages unavailable, the others 0
    fresh = GpuTimer(ctx, wait=False)
    with fresh.section("stage:part"):
        pass
    assert np.isnan(fresh.frame_timings(("stage", "other"))["timings"]["stage"])
    assert fresh.frame_timings(("stage", "other"))["timings"]["other"] == 0.0
    # wait=True reads this frame's own sections, waiting for them (the behaviour before the ring)
    timer.wait = True
    assert set(timer.ms) == {"next"} and timer.lag == 0
    assert timer.frame_timings(("next",))["timings_lag"] == 0
    # the timer off: nothing measured, every stage unavailable
    timer.enabled = False
    assert all(np.isnan(v) for v in timer.frame_timings(("next", "slow"))["timings"].values())
    timer.enabled, timer.wait = True, False
    # a timer nobody reads keeps a bounded ring of pending frames
    from dmrt.gl.timer import MAX_PENDING_FRAMES

    for _ in range(3 * MAX_PENDING_FRAMES):
        frame("x", 1)
        timer.reset()
    assert len(timer._ring) <= MAX_PENDING_FRAMES
    for t in (timer, fresh):
        t.release()
    for obj in (vao, vbo, fbo, prog):
        obj.release()


def test_unmeasured_times_print_as_unavailable():
    from dmrt.gl.timer import format_ms, format_timings

    assert format_ms(0.414) == "0.41 ms" and format_ms(float("nan")) == "n/a" and format_ms(None) == "n/a"
    assert format_timings({"a": float("nan"), "off": 0.0}) == "GPU times unavailable"
    assert format_timings({"a": 1.0, "b": float("nan")}) == "a 1.00 ms, b n/a"


def test_timer_detects_work_that_never_ran(ctx):
    """A hardware GPU whose context stopped executing (an H200 after a fault) reads 0 ns for every
    section and reports no GL error: that must raise instead of passing stale frames on."""
    from dmrt.gl.timer import require_gpu_work

    with pytest.raises(RuntimeError, match="executed none of the work while testing"):
        require_gpu_work({"visibility": 0.0, "raytracing": 0.0}, "testing")
    require_gpu_work({"visibility": 0.0, "raytracing": 1e-6}, "testing")  # some work ran
    require_gpu_work({}, "testing")  # nothing timed: nothing to judge
    # a real dispatch passes on any driver (llvmpipe: 1 ns, and its times are not judged at all)
    timer = GpuTimer(ctx)
    buf = ctx.buffer(reserve=64 * 4)
    buf.bind_to_storage_buffer(0)
    with timer.section("dispatch"):
        load_program(ctx, "fill_u32").run(1)
    timer.check_executed("testing")


def test_gl_errors_raise(ctx):
    from dmrt.gl import check_gl

    check_gl(ctx, "testing")  # a clean flag passes
    too_many = ctx.info["GL_MAX_COMPUTE_WORK_GROUP_COUNT"][0] + 1
    load_program(ctx, "fill_u32").run(too_many)  # GL_INVALID_VALUE: the dispatch does not run
    with pytest.raises(RuntimeError, match="OpenGL error GL_INVALID_VALUE while testing"):
        check_gl(ctx, "testing")
    check_gl(ctx, "testing")  # reading the flag clears it


def test_allocation_beyond_gpu_memory_names_the_budget(ctx):
    """An array that no GPU holds (2,048 RGBA8 layers of 16384^2: 2.2 TB) sets GL_OUT_OF_MEMORY;
    check_fits turns it into a ConfigError naming the budget option, and clears the flag."""
    from dmrt.errors import ConfigError
    from dmrt.gl.context import check_fits

    check_fits(ctx, "cache_mb", "nothing")  # a clean flag passes
    side, layers = 16384, ctx.info["GL_MAX_ARRAY_TEXTURE_LAYERS"]
    tex = ctx.texture_array((side, side, layers), 4)
    try:
        with pytest.raises(ConfigError, match="--cache-mb: a huge array: more than this GPU's memory holds"):
            check_fits(ctx, "cache_mb", "a huge array")
    finally:
        tex.release()
    check_fits(ctx, "cache_mb", "nothing")


def test_mapped_buffer_reads_what_the_gpu_wrote(ctx):
    """A persistently mapped buffer (the status records' storage): its initial bytes, then what
    passes wrote - read after their fence, after an unfenced bind (the read fences it), after a CPU
    write the next pass overwrites in part, and a GPU buffer's copy (``copy_from``)."""
    from dmrt.gl.mapped import MappedBuffer

    program = ctx.compute_shader("""#version 430
        layout(local_size_x = 8) in;
        layout(std430, binding = 3) buffer B { uint v[]; };
        uniform uint u_add;
        void main() { if (gl_LocalInvocationIndex < 4u) v[gl_LocalInvocationIndex] += u_add; }""")
    buf = MappedBuffer(ctx, np.arange(8, dtype=np.uint32).tobytes())
    try:
        np.testing.assert_array_equal(np.frombuffer(buf.read(), np.uint32), np.arange(8))
        for add, fence in ((10, True), (100, False)):
            buf.bind_to_storage_buffer(3)
            program["u_add"].value = add
            program.run(1)
            if fence:
                buf.written()
            got = np.frombuffer(buf.read(), np.uint32)
        np.testing.assert_array_equal(got, [110, 111, 112, 113, 4, 5, 6, 7])
        buf.write(np.full(8, 7, np.uint32).tobytes())
        buf.bind_to_storage_buffer(3)
        program.run(1)
        np.testing.assert_array_equal(np.frombuffer(buf.read(), np.uint32), [107] * 4 + [7] * 4)
        with pytest.raises(ValueError, match="do not fit"):
            buf.write(bytes(33))
        src = ctx.buffer(np.arange(20, 28, dtype=np.uint32).tobytes())  # a GPU buffer, copied on the GPU
        src.bind_to_storage_buffer(3)
        program.run(1)  # the copy follows this pass's writes
        buf.copy_from(src, 16)
        np.testing.assert_array_equal(np.frombuffer(buf.read(), np.uint32), [120, 121, 122, 123] + [7] * 4)
        src.release()
    finally:
        buf.release()
    with pytest.raises(RuntimeError, match="released"):
        buf.read()
