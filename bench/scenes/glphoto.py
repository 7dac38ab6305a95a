"""The synthetic scenes' matte photographs rasterized by OpenGL: :meth:`Studio.photograph` on a GPU.

Embree and numpy shading make ~9 photos of 1024x684 a second on 16 cores, 20 minutes for the
10,240 photos of the ``many`` preset. :class:`GLPhotographer` rasterizes the photographed mesh
through each camera (``shaders/synth_photograph.glsl``) and computes per pixel what
:meth:`Studio.photograph` computes per ray; the box filter, gain and rounding are the same numpy
code (:func:`~bench.scenes.synthetic.develop`). It covers matte photos only (``specular`` 0): the
highlight's shadow rays stay with Embree, which also stays the truth for held-out views.

The photos agree with Embree's except where float32 and float64 hit points fall on different sides
of a texel boundary and where rasterization and Embree give a triangle edge's pixel to different
triangles (``tests/test_synth_gl.py`` measures both).
"""

from __future__ import annotations

import ctypes

import moderngl
import numpy as np

from bench.scenes.synthetic import Studio, SynthConfig, develop, shade
from dmrt.camera import Camera
from dmrt.errors import ConfigError
from dmrt.gl import abi, check_gl, get_context, load_program, set_uniforms

FACE = np.dtype([("plane", "f4", 4), ("material", "i4"), ("axis", "i4"), ("shade_front", "f4"),
                 ("shade_back", "f4")])  # std430 Face of the shader, 32 bytes
# near plane, metres: only clips, the depth test reads the ray's own camera z (cameras stand >= 0.3 m
# clear of every surface)
NEAR = 1e-3

_GL_TEXTURE_2D, _GL_DEPTH_COMPONENT32F, _GL_DEPTH_COMPONENT, _GL_FLOAT = 0x0DE1, 0x8CAC, 0x1902, 0x1406


def choose_photographer(config: SynthConfig) -> str:
    """``"gl"`` or ``"embree"``: the photographer ``config.photographer`` asks for ("auto": gl when
    the photos are matte and an OpenGL 4.3 context can be made).

    Raises
    ------
    ConfigError
        ``"gl"`` asked for and no OpenGL 4.3 context (the message says what to install).
    """
    if config.photographer == "embree" or config.specular > 0:  # "gl" with specular is refused earlier
        return "embree"
    try:
        get_context(430)
    except RuntimeError as exc:
        if config.photographer == "gl":
            raise ConfigError("photographer", str(exc)) from exc
        return "embree"
    return "gl"


def _depth32f(ctx: moderngl.Context, size: tuple[int, int]) -> moderngl.Texture:
    """A GL_DEPTH_COMPONENT32F texture: moderngl makes 24-bit depth textures only, so its storage is
    specified again as float (a texture made by glTexImage2D may be)."""
    tex = ctx.depth_texture(size)
    egl = ctypes.CDLL("libEGL.so.1")
    egl.eglGetProcAddress.restype, egl.eglGetProcAddress.argtypes = ctypes.c_void_p, [ctypes.c_char_p]
    address = egl.eglGetProcAddress(b"glTexImage2D")
    if not address:  # EGL < 1.5 need not return core functions: calling NULL would end the process
        raise ConfigError("photographer", "gl: this EGL gives no glTexImage2D for a float depth buffer: "
                                          "use --photographer embree")
    tex_image_2d = ctypes.CFUNCTYPE(None, *[ctypes.c_uint, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_int,
                                            ctypes.c_int, ctypes.c_uint, ctypes.c_uint, ctypes.c_void_p])(address)
    tex.use(0)
    tex_image_2d(_GL_TEXTURE_2D, 0, _GL_DEPTH_COMPONENT32F, size[0], size[1], 0, _GL_DEPTH_COMPONENT, _GL_FLOAT, None)
    check_gl(ctx, "making a float depth buffer for the synthetic photos")
    return tex


class GLPhotographer:
    """Matte photographs of a :class:`Studio` rendered with OpenGL.

    Parameters
    ----------
    studio : Studio
        With ``config.specular == 0``.
    ctx : moderngl.Context, optional
        GL 4.3+; default the process-wide context (:func:`dmrt.gl.get_context`).
    """

    def __init__(self, studio: Studio, ctx: moderngl.Context | None = None):
        if studio.config.specular > 0:
            raise ConfigError("photographer", "'gl' takes matte photos only (specular 0): the highlight's "
                                              "shadows are Embree's")
        self.studio, self.ctx = studio, ctx or get_context(430)
        geom, normals = studio.photo_geom, studio.photo_raycaster.face_normals
        materials = studio.materials
        self.program = load_program(self.ctx, "synth_photograph", {"N_MATERIALS": len(materials)})
        faces = np.zeros(len(geom.faces), FACE)
        faces["plane"][:, :3] = normals
        faces["plane"][:, 3] = np.einsum("ij,ij->i", normals, geom.vertices[geom.faces[:, 0]])
        faces["material"] = geom.face_material
        faces["axis"] = np.argmax(np.abs(normals), axis=1)  # numpy's tie rule, as albedo() applies it
        faces["shade_front"], faces["shade_back"] = shade(normals), shade(-normals)
        self.faces = self.ctx.buffer(faces.tobytes())
        self.vertices = self.ctx.buffer(geom.vertices.astype("f4").tobytes())
        self.indices = self.ctx.buffer(geom.faces.astype("i4").tobytes())
        self.vao = self.ctx.vertex_array(self.program, [(self.vertices, "3f", "in_position")],
                                         index_buffer=self.indices, index_element_size=4)
        h = max(m.texture.shape[0] for m in materials)
        w = max(m.texture.shape[1] for m in materials)
        layers = np.zeros((len(materials), h, w, 3), np.float32)
        for k, m in enumerate(materials):
            layers[k, :m.texture.shape[0], :m.texture.shape[1]] = m.texture
        self.textures = self.ctx.texture_array((w, h, len(materials)), 3, layers.tobytes(), dtype="f4")
        self.textures.filter = moderngl.NEAREST, moderngl.NEAREST
        set_uniforms(self.program, u_textures=0,
                     u_texture_size=np.array([m.texture.shape[1::-1] for m in materials], np.int32),
                     u_texels_per_metre=np.array([max(m.texture.shape[:2]) / m.tile for m in materials]))
        lo, hi = geom.vertices.min(0), geom.vertices.max(0)
        self.corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        self._targets: dict = {}
        check_gl(self.ctx, "uploading the synthetic scene's mesh")

    def _target(self, size: tuple[int, int]):
        if size not in self._targets:
            color = self.ctx.texture(size, 4, dtype="f4")
            depth = _depth32f(self.ctx, size)
            self._targets[size] = (color, depth, self.ctx.framebuffer([color], depth))
        return self._targets[size][2]

    def colors(self, camera: Camera) -> np.ndarray:
        """(height, width, 3) float32 ``albedo x shade`` of each pixel centre's surface (0 where
        the ray leaves the scene) through the scene-local ``camera``: :meth:`Studio.photograph`'s
        ``rgb`` before the box filter."""
        fbo = self._target((camera.width, camera.height))
        far = float(np.linalg.norm(self.corners - camera.center, axis=1).max()) + 1.0
        set_uniforms(self.program, u_view_projection=camera.gl_view_projection(NEAR, far).T.ravel(),
                     u_camera_to_world=camera.R.ravel(), u_center=tuple(camera.center),
                     u_intrinsics=(camera.fx, camera.fy, camera.cx, camera.cy), u_far=far)
        with self.ctx.scope(fbo, enable_only=moderngl.DEPTH_TEST):
            self.ctx.depth_func = "<"
            fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            self.textures.use(0)
            self.faces.bind_to_storage_buffer(abi.B_SYNTH_FACES)
            self.vao.render(moderngl.TRIANGLES)
            data = fbo.read(components=3, dtype="f4")
        check_gl(self.ctx, "rendering a synthetic photo")
        return np.frombuffer(data, np.float32).reshape(camera.height, camera.width, 3)

    def photograph(self, camera: Camera, gain=None, world: bool = False) -> np.ndarray:
        """(h, w, 3) uint8: :meth:`Studio.photograph` (same arguments) rasterized."""
        if world:
            camera = camera.relative_to(self.studio.config.offset)
        s = self.studio.config.supersample
        return develop(self.colors(camera.scaled(camera.width * s, camera.height * s)), camera, s, gain)

    def __enter__(self) -> "GLPhotographer":
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def release(self) -> None:
        """Free the GPU objects (the cached program stays with the context)."""
        for obj in (self.vao, self.faces, self.vertices, self.indices, self.textures,
                    *(o for t in self._targets.values() for o in t)):
            obj.release()
        self._targets.clear()
