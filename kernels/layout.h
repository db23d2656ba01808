// Records shared by the kernels and the host, as float offsets. This header is
// valid C++ and OpenCL C: host/render/renderer.cpp includes it, and the host puts it
// in front of kernels/common.cl in every program it builds, so the two sides
// cannot drift apart.
#ifndef AG2GS_KERNELS_LAYOUT_H
#define AG2GS_KERNELS_LAYOUT_H

// Screen tiles are TILE x TILE pixels (binning, blending, the staging batches).
#ifndef TILE
#define TILE 16
#endif

// Blending: a Gaussian adds to a pixel when its alpha is at least ALPHA_MIN
// (clamped to ALPHA_MAX); a pixel stops once its transmittance would fall
// below T_MIN.
#define ALPHA_MIN (1.0f / 255.0f)
#define ALPHA_MAX 0.99f
#define T_MIN 1e-4f

// Per-Gaussian record written by projection and read by blending, REC_SIZE floats.
#define REC_U 0        // pixel centre x
#define REC_V 1        // pixel centre y
#define REC_CA 2       // conic (inverse 2D covariance): a, b, c
#define REC_CB 3
#define REC_CC 4
#define REC_OPACITY 5
#define REC_Z 6        // camera-space depth
#define REC_M 7        // depth mapped for the distortion term
#define REC_RGB 8      // [3] colour from the spherical harmonics
#define REC_FEAT 11    // [3] semantic feature
#define REC_THR 14     // ln(255 opacity): alpha >= 1/255 needs sigma <= REC_THR
#define REC_CM 15      // cC - cB^2 / cA: sigma >= 0.5 dy^2 REC_CM on a row at offset dy
#define REC_SIZE 16

// Per-intersection gradient slot written by blend backward, G2_SIZE floats.
#define G2_U 0
#define G2_V 1
#define G2_CA 2
#define G2_CB 3
#define G2_CC 4
#define G2_OPACITY 5
#define G2_RGB 6       // [3]
#define G2_FEAT 9      // [3]
#define G2_Z 12
#define G2_SIZE 13

// Camera block, CAM_SIZE floats (host: pack_camera in host/render/renderer.cpp).
#define CAM_R 0        // [9] world->camera rotation, row-major
#define CAM_T 9        // [3]
#define CAM_FX 12
#define CAM_FY 13
#define CAM_CX 14
#define CAM_CY 15
#define CAM_W 16
#define CAM_H 17
#define CAM_NEAR 18
#define CAM_POS 19     // [3] camera centre in world space
#define CAM_DNEAR 22   // distortion depth mapping: near and far
#define CAM_DFAR 23
#define CAM_BG 24      // [3] background colour
#define CAM_LOWPASS 27 // screen-space low-pass added to the 2D covariance (px^2)
#define CAM_SIZE 32

#endif  // AG2GS_KERNELS_LAYOUT_H
