"""OpenGL plumbing: one headless context per process, the GLSL program loader, GPU stage timers."""

from dmrt.gl.context import check_gl, create_context, get_context, renderer_info
from dmrt.gl.shaders import ShaderError, load_program, set_uniforms
from dmrt.gl.timer import GpuTimer

__all__ = ["check_gl", "create_context", "get_context", "renderer_info", "load_program", "set_uniforms", "ShaderError",
           "GpuTimer"]
