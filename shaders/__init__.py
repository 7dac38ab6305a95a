"""GLSL programs, one file per program; loaded by :mod:`dmrt.gl.shaders`."""

from pathlib import Path

SHADER_DIR = Path(__file__).resolve().parent
