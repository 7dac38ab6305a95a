// INT64 1 (NVIDIA): 64-bit integers and their atomics, for one-pass (depth bits << 32 | label)
// z-buffering. Included before any declaration; no #version.
#ifndef INT64
#define INT64 0
#endif
#if INT64
#extension GL_ARB_gpu_shader_int64 : require
#extension GL_NV_shader_atomic_int64 : require
#endif
