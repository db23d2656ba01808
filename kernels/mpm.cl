// MLS-MPM (moving least squares material point method) with quadratic
// B-splines and APIC transfers: host wrapper host/physics/mpm.h, the method
// in docs/design.md, "Physics".
//
// A substep: mpm_keys (each particle's base cell; the host sorts by it) ->
// mpm_particle_stress (plasticity, then the stress and momentum each
// particle will hand to its 27 nodes, in sorted order) -> mpm_grid (every
// node gathers from the particles of its 27 neighbouring cells in sorted
// order, then adds gravity and applies the walls and the ground) -> mpm_g2p
// (velocities, APIC matrices, positions and F back on the particles).
// Gathering in a fixed order instead of scattering with atomics makes every
// substep bit-identical across runs and thread counts.
//
// Units: the box [0, 1]^3, GRID cells per side, dx = 1 / GRID, +z up.

#define MPM_BOUND 3      // cells of wall at each side of the box
// The ground holds the nodes up to 1.5 cells above it: the quadratic
// B-spline's reach, so a particle lying on the ground takes its velocity only
// from held nodes and the ground's friction acts on it in full. (Holding only
// the nodes at or below the ground gave the lowest particles about 10% of
// their weight from held nodes: sand slid on a floor of friction 1.)
#define GROUND_BAND 1.5f
#define MAT_SIZE 12      // per material: kind, mu, lambda, yield, alpha, softening, force (3), unused (3)
#define PD_SIZE 16       // per sorted particle: x (3), mass, momentum (3), affine Q (9)

// Base cell of a position: the lowest of the 3 nodes per axis a quadratic
// B-spline reaches, clamped so that all 3 stay inside the grid.
inline int3 mpm_base(float3 x, float inv_dx, int grid) {
  int3 b = convert_int3(floor(x * inv_dx - 0.5f));
  return clamp(b, (int3)(0), (int3)(grid - 3));
}

// Quadratic B-spline weights of a particle at fx (cell units from its base
// cell) for the nodes base + 0, 1, 2 on one axis.
inline float3 bspline_weights(float fx) {
  float a = 1.5f - fx, b = fx - 1.f, c = fx - 0.5f;
  return (float3)(0.5f * a * a, 0.75f - b * b, 0.5f * c * c);
}
inline float bspline_pick(float3 w, int d) { return d == 0 ? w.x : (d == 1 ? w.y : w.z); }
// bspline_weights(fx) picked at node d, computing that weight alone (the same
// expression, so the same bits).
inline float bspline_weight(float fx, int d) {
  if (d == 0) {
    const float a = 1.5f - fx;
    return 0.5f * a * a;
  }
  if (d == 1) {
    const float b = fx - 1.f;
    return 0.75f - b * b;
  }
  const float c = fx - 0.5f;
  return 0.5f * c * c;
}

inline mat3 mat3_load_g(__global const float* p) {
  mat3 r;
  for (int i = 0; i < 9; ++i) r.m[i] = p[i];
  return r;
}
inline void mat3_store_g(mat3 a, __global float* p) {
  for (int i = 0; i < 9; ++i) p[i] = a.m[i];
}
inline float mat3_det(mat3 a) {
  return a.m[0] * (a.m[4] * a.m[8] - a.m[5] * a.m[7]) - a.m[1] * (a.m[3] * a.m[8] - a.m[5] * a.m[6]) +
         a.m[2] * (a.m[3] * a.m[7] - a.m[4] * a.m[6]);
}
inline float3 mat3_col(mat3 a, int j) { return (float3)(a.m[j], a.m[3 + j], a.m[6 + j]); }
inline void mat3_set_col(mat3* a, int j, float3 c) {
  a->m[j] = c.x;
  a->m[3 + j] = c.y;
  a->m[6 + j] = c.z;
}
// U diag(s) V^T
inline mat3 mat3_usv(mat3 U, float3 s, mat3 V) {
  mat3 r;
  float sv[3] = {s.x, s.y, s.z};
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      r.m[3 * i + j] = U.m[3 * i] * sv[0] * V.m[3 * j] + U.m[3 * i + 1] * sv[1] * V.m[3 * j + 1] +
                       U.m[3 * i + 2] * sv[2] * V.m[3 * j + 2];
  return r;
}

// SVD of F = U diag(sig) V^T with U, V rotations (det +1); the smallest
// singular value carries the sign of det F (an inverted element). From the
// eigenvectors of F^T F by cyclic Jacobi rotations: at most 4 sweeps (3x3
// symmetric Jacobi converges quadratically), a rotation skipped once its
// off-diagonal entry is below float resolution of the diagonal (rotating
// it away would move the diagonal by less than a rounding).
inline void svd3(mat3 F, mat3* Uo, float3* so, mat3* Vo) {
  mat3 A = mat3_mul(mat3_transpose(F), F);
  mat3 V = {{1.f, 0.f, 0.f, 0.f, 1.f, 0.f, 0.f, 0.f, 1.f}};
  // Unrolled: constant p and q keep A and V in registers.
#pragma unroll
  for (int sweep = 0; sweep < 4; ++sweep) {
#pragma unroll
    for (int pair = 0; pair < 3; ++pair) {
      const int p = pair == 2 ? 1 : 0, q = pair == 0 ? 1 : 2;
      const float apq = A.m[3 * p + q];
      if (fabs(apq) <= 1e-7f * (fabs(A.m[3 * p + p]) + fabs(A.m[3 * q + q])) || fabs(apq) < 1e-30f) continue;
      const float theta = (A.m[3 * q + q] - A.m[3 * p + p]) / (2.f * apq);
      const float t = (theta >= 0.f ? 1.f : -1.f) / (fabs(theta) + sqrt(theta * theta + 1.f));
      const float c = 1.f / sqrt(t * t + 1.f), s = t * c;
      // A <- J^T A J, V <- V J with J the rotation in the (p, q) plane.
#pragma unroll
      for (int k = 0; k < 3; ++k) {
        const float akp = A.m[3 * k + p], akq = A.m[3 * k + q];
        A.m[3 * k + p] = c * akp - s * akq;
        A.m[3 * k + q] = s * akp + c * akq;
      }
#pragma unroll
      for (int k = 0; k < 3; ++k) {
        const float apk = A.m[3 * p + k], aqk = A.m[3 * q + k];
        A.m[3 * p + k] = c * apk - s * aqk;
        A.m[3 * q + k] = s * apk + c * aqk;
      }
#pragma unroll
      for (int k = 0; k < 3; ++k) {
        const float vkp = V.m[3 * k + p], vkq = V.m[3 * k + q];
        V.m[3 * k + p] = c * vkp - s * vkq;
        V.m[3 * k + q] = s * vkp + c * vkq;
      }
    }
  }
  if (mat3_det(V) < 0.f) mat3_set_col(&V, 2, -mat3_col(V, 2));
  float sig[3];
  mat3 U;
  for (int j = 0; j < 3; ++j) sig[j] = sqrt(fmax(A.m[4 * j], 0.f));
  // U's columns F v_j / sig_j, the smallest one (least reliable) as the cross
  // product of the other two, so that U is a rotation.
  int small = 0;
  for (int j = 1; j < 3; ++j)
    if (sig[j] < sig[small]) small = j;
  const int a = (small + 1) % 3, b = (small + 2) % 3;
  float3 ua = mat3_vec(F, mat3_col(V, a)), ub = mat3_vec(F, mat3_col(V, b));
  ua = sig[a] > 1e-20f ? ua / sig[a] : (float3)(1.f, 0.f, 0.f);
  ub = ub - dot(ua, ub) * ua;
  const float nb = length(ub);
  if (nb > 1e-20f) {
    ub /= nb;
  } else {  // any unit vector orthogonal to ua
    ub = fabs(ua.x) < 0.9f ? (float3)(1.f, 0.f, 0.f) : (float3)(0.f, 1.f, 0.f);
    ub = normalize(ub - dot(ua, ub) * ua);
  }
  mat3_set_col(&U, a, ua);
  mat3_set_col(&U, b, ub);
  mat3_set_col(&U, small, cross(ua, ub));  // (a, b, small) is a cyclic order: det U = +1
  // F v_small = sig_small * s u_small with s = +1 or -1: the sign of det F.
  if (dot(mat3_vec(F, mat3_col(V, small)), mat3_col(U, small)) < 0.f) sig[small] = -sig[small];
  *Uo = U;
  *Vo = V;
  *so = (float3)(sig[0], sig[1], sig[2]);
}

// Kirchhoff stress tau = P F^T of the material, after its plastic return
// mapping has projected F (written back through *F) and updated *plastic.
inline mat3 material_stress(__global const float* mp, mat3* Fp, float* plastic) {
  const int kind = (int)mp[0];
  const float mu = mp[1], la = mp[2];
  mat3 F = *Fp, U, V;
  float3 sig;
  svd3(F, &U, &sig, &V);
  mat3 tau;
  if (kind == 0) {
    // Fixed-corotated: P = 2 mu (F - R) + lambda (J - 1) J F^-T, R = U V^T.
    const float J = sig.x * sig.y * sig.z;
    const mat3 R = mat3_mul(U, mat3_transpose(V));
    const mat3 FT = mat3_transpose(F);
    mat3 d;
    for (int i = 0; i < 9; ++i) d.m[i] = F.m[i] - R.m[i];
    tau = mat3_mul(d, FT);
    for (int i = 0; i < 9; ++i) tau.m[i] *= 2.f * mu;
    for (int i = 0; i < 3; ++i) tau.m[4 * i] += la * (J - 1.f) * J;
    return tau;
  }
  // Hencky strain eps = log sig (inverted elements are clamped to a small
  // positive stretch: these materials flow instead of inverting).
  float3 eps = log(fmax(sig, (float3)(1e-4f)));
  const float tr = eps.x + eps.y + eps.z;
  float3 dev = eps - tr / 3.f;
  const float ndev = length(dev);
  if (kind == 1 || kind == 3) {
    // von Mises: the deviatoric strain is held within yield / (2 mu);
    // plasticine's yield falls as plastic strain accumulates.
    const float yield = kind == 3 ? mp[3] / (1.f + mp[5] * *plastic) : mp[3];
    const float dg = ndev - yield / (2.f * mu);
    if (dg > 0.f) {
      eps -= dg / ndev * dev;
      *plastic += dg;
    }
  } else if (kind == 2) {
    // Drucker-Prager (Klar et al. 2016): expansion goes to the cone's tip,
    // compression beyond the friction cone is projected back onto it.
    if (tr >= 0.f || ndev <= 0.f) {
      *plastic += length(eps);
      eps = (float3)(0.f);
    } else {
      const float dg = ndev + (3.f * la + 2.f * mu) / (2.f * mu) * tr * mp[4];
      if (dg > 0.f) {
        eps -= dg / ndev * dev;
        *plastic += dg;
      }
    }
  }
  const float3 s = exp(eps);
  *Fp = mat3_usv(U, s, V);
  // StVK on the Hencky strain: tau = U (2 mu eps + lambda tr(eps) I) U^T.
  const float tr2 = eps.x + eps.y + eps.z;
  return mat3_usv(U, 2.f * mu * eps + la * tr2, U);
}

__kernel void mpm_keys(int n, float inv_dx, int grid,
                       __global const float* x,  // [N,3]
                       __global int* keys) {     // [N] base cell, (bx * grid + by) * grid + bz
  const int p = get_global_id(0);
  if (p >= n) return;
  const int3 b = mpm_base(vload3(p, x), inv_dx, grid);
  keys[p] = (b.x * grid + b.y) * grid + b.z;
}

__kernel void mpm_particle_stress(int n, float dt, float inv_dx, int forces_on,
                                  __global const int* order,       // [N] particles sorted by cell
                                  __global const float* x,         // [N,3]
                                  __global const float* v,         // [N,3]
                                  __global float* F,               // [N,9] projected by plasticity
                                  __global const float* C,         // [N,9]
                                  __global const float* volume,    // [N]
                                  __global const float* mass,      // [N]
                                  __global float* plastic,         // [N]
                                  __global const int* material,    // [N]
                                  __global const float* mat_params,  // [M,MAT_SIZE]
                                  __global float* pdata) {         // [N,PD_SIZE] by sorted index
  const int s = get_global_id(0);
  if (s >= n) return;
  const int p = order[s];
  __global const float* mp = mat_params + material[p] * MAT_SIZE;
  mat3 Fp = mat3_load_g(F + 9 * p);
  float pl = plastic[p];
  const mat3 tau = material_stress(mp, &Fp, &pl);
  mat3_store_g(Fp, F + 9 * p);
  plastic[p] = pl;
  // MLS-MPM: the stress enters as an affine momentum term,
  // Q = -dt V0 (4 / dx^2) tau + m C (Hu et al. 2018, eq. 29 with D^-1 = 4 / dx^2).
  const float m = mass[p];
  const float k = -dt * volume[p] * 4.f * inv_dx * inv_dx;
  __global float* o = pdata + (size_t)s * PD_SIZE;
  const float3 xp = vload3(p, x);
  float3 mv = m * vload3(p, v);
  if (forces_on) mv += m * dt * (float3)(mp[6], mp[7], mp[8]);
  o[0] = xp.x;
  o[1] = xp.y;
  o[2] = xp.z;
  o[3] = m;
  o[4] = mv.x;
  o[5] = mv.y;
  o[6] = mv.z;
  for (int i = 0; i < 9; ++i) o[7 + i] = k * tau.m[i] + m * C[9 * p + i];
}

// One work-item per active node: `active` lists the nodes of the node box
// [nlo, nlo + ndim) that some particle reaches (the others are never read).
// The particles' base cells span [clo, clo + cdim) and cell_start indexes
// that box.
__kernel void mpm_grid(int n_active, int grid, float dt, float dx, float inv_dx, int4 nlo, int4 ndim, int4 clo,
                       int4 cdim, float4 gravity, float ground, float friction,
                       float keep_speed,                // 1 / (1 + damping dt): 1 undamped
                       __global const int* active,      // [n_active] node ids in the node box
                       __global const int* cell_start,  // [cells of the cell box + 1] into the sorted particles
                       __global const float* pdata,     // [N,PD_SIZE] sorted
                       __global float* grid_v) {        // [nodes of the node box,4] velocity, mass
  const int a = get_global_id(0);
  if (a >= n_active) return;
  const int id = active[a];
  const int3 node = (int3)(id / (ndim.y * ndim.z), (id / ndim.z) % ndim.y, id % ndim.z) + nlo.xyz;
  float3 mom = (float3)(0.f);
  float m = 0.f;
  // Unrolled (here and in mpm_g2p): constant offsets fold the choice of
  // weight; the same sums in the same order.
#pragma unroll
  for (int ox = 0; ox < 3; ++ox)
#pragma unroll
    for (int oy = 0; oy < 3; ++oy)
#pragma unroll
      for (int oz = 0; oz < 3; ++oz) {
        const int3 c = node - (int3)(ox, oy, oz) - clo.xyz;
        if (c.x < 0 || c.y < 0 || c.z < 0 || c.x >= cdim.x || c.y >= cdim.y || c.z >= cdim.z) continue;
        const int ci = (c.x * cdim.y + c.y) * cdim.z + c.z;
        const int3 base = node - (int3)(ox, oy, oz);
        for (int s = cell_start[ci]; s < cell_start[ci + 1]; ++s) {
          __global const float* pd = pdata + (size_t)s * PD_SIZE;
          const float3 fx = (float3)(pd[0], pd[1], pd[2]) * inv_dx - convert_float3(base);
          const float w = bspline_weight(fx.x, ox) * bspline_weight(fx.y, oy) * bspline_weight(fx.z, oz);
          const float3 dpos = ((float3)((float)ox, (float)oy, (float)oz) - fx) * dx;
          const float3 q = (float3)(pd[7] * dpos.x + pd[8] * dpos.y + pd[9] * dpos.z,
                                    pd[10] * dpos.x + pd[11] * dpos.y + pd[12] * dpos.z,
                                    pd[13] * dpos.x + pd[14] * dpos.y + pd[15] * dpos.z);
          mom += w * ((float3)(pd[4], pd[5], pd[6]) + q);
          m += w * pd[3];
        }
      }
  float3 vel = (float3)(0.f);
  if (m > 0.f) {
    vel = (mom / m + dt * gravity.xyz) * keep_speed;
    // Walls: no velocity out of the box within MPM_BOUND cells of a side.
    if (node.x < MPM_BOUND && vel.x < 0.f) vel.x = 0.f;
    if (node.y < MPM_BOUND && vel.y < 0.f) vel.y = 0.f;
    if (node.z < MPM_BOUND && vel.z < 0.f) vel.z = 0.f;
    if (node.x > grid - MPM_BOUND && vel.x > 0.f) vel.x = 0.f;
    if (node.y > grid - MPM_BOUND && vel.y > 0.f) vel.y = 0.f;
    if (node.z > grid - MPM_BOUND && vel.z > 0.f) vel.z = 0.f;
    // The ground: nodes up to GROUND_BAND cells above it stop moving down
    // (they may leave it), and Coulomb friction takes up to friction x the
    // normal speed lost off their sliding speed.
    if (ground >= 0.f && (float)node.z * dx <= ground + GROUND_BAND * dx && vel.z < 0.f) {
      const float vt = sqrt(vel.x * vel.x + vel.y * vel.y);
      const float keep = vt > 0.f ? fmax(1.f + friction * vel.z / vt, 0.f) : 0.f;
      vel.x *= keep;
      vel.y *= keep;
      vel.z = 0.f;
    }
  }
  vstore4((float4)(vel, m), id, grid_v);
}

__kernel void mpm_g2p(int n, int grid, float dt, float dx, float inv_dx, int4 nlo, int4 ndim,
                      __global const float* grid_v,  // [nodes of the node box,4]
                      __global float* x,             // [N,3]
                      __global float* v,             // [N,3]
                      __global float* F,             // [N,9]
                      __global float* C) {           // [N,9]
  const int p = get_global_id(0);
  if (p >= n) return;
  const float3 xp = vload3(p, x);
  const int3 base = mpm_base(xp, inv_dx, grid);
  const float3 fx = xp * inv_dx - convert_float3(base);
  const float3 wx = bspline_weights(fx.x), wy = bspline_weights(fx.y), wz = bspline_weights(fx.z);
  float3 vel = (float3)(0.f);
  mat3 B = {{0.f, 0.f, 0.f, 0.f, 0.f, 0.f, 0.f, 0.f, 0.f}};
#pragma unroll
  for (int ox = 0; ox < 3; ++ox)
#pragma unroll
    for (int oy = 0; oy < 3; ++oy)
#pragma unroll
      for (int oz = 0; oz < 3; ++oz) {
        const int3 nl = base + (int3)(ox, oy, oz) - nlo.xyz;
        const float4 g = vload4((nl.x * ndim.y + nl.y) * ndim.z + nl.z, grid_v);
        const float w = bspline_pick(wx, ox) * bspline_pick(wy, oy) * bspline_pick(wz, oz);
        const float3 dpos = ((float3)((float)ox, (float)oy, (float)oz) - fx) * dx;
        const float3 wv = w * g.xyz;
        vel += wv;
        B.m[0] += wv.x * dpos.x; B.m[1] += wv.x * dpos.y; B.m[2] += wv.x * dpos.z;
        B.m[3] += wv.y * dpos.x; B.m[4] += wv.y * dpos.y; B.m[5] += wv.y * dpos.z;
        B.m[6] += wv.z * dpos.x; B.m[7] += wv.z * dpos.y; B.m[8] += wv.z * dpos.z;
      }
  const float d_inv = 4.f * inv_dx * inv_dx;
  mat3 Cn;
  for (int i = 0; i < 9; ++i) Cn.m[i] = d_inv * B.m[i];
  // F <- (I + dt C) F
  mat3 G;
  for (int i = 0; i < 9; ++i) G.m[i] = dt * Cn.m[i];
  G.m[0] += 1.f;
  G.m[4] += 1.f;
  G.m[8] += 1.f;
  const mat3 Fn = mat3_mul(G, mat3_load_g(F + 9 * p));
  vstore3(vel, p, v);
  vstore3(xp + dt * vel, p, x);
  mat3_store_g(Cn, C + 9 * p);
  mat3_store_g(Fn, F + 9 * p);
}

// ------------------------------------------------------------ Gaussians
// R(q) -> q for a rotation matrix (Shepperd's method: the largest of the
// four candidates' denominators, so no division by a small number).
inline float4 rotmat_to_quat(mat3 R) {
  const float tr = R.m[0] + R.m[4] + R.m[8];
  float4 q;  // w x y z
  if (tr > 0.f) {
    const float s = 2.f * sqrt(tr + 1.f);
    q = (float4)(0.25f * s, (R.m[7] - R.m[5]) / s, (R.m[2] - R.m[6]) / s, (R.m[3] - R.m[1]) / s);
  } else if (R.m[0] > R.m[4] && R.m[0] > R.m[8]) {
    const float s = 2.f * sqrt(1.f + R.m[0] - R.m[4] - R.m[8]);
    q = (float4)((R.m[7] - R.m[5]) / s, 0.25f * s, (R.m[1] + R.m[3]) / s, (R.m[2] + R.m[6]) / s);
  } else if (R.m[4] > R.m[8]) {
    const float s = 2.f * sqrt(1.f + R.m[4] - R.m[0] - R.m[8]);
    q = (float4)((R.m[2] - R.m[6]) / s, (R.m[1] + R.m[3]) / s, 0.25f * s, (R.m[5] + R.m[7]) / s);
  } else {
    const float s = 2.f * sqrt(1.f + R.m[8] - R.m[0] - R.m[4]);
    q = (float4)((R.m[3] - R.m[1]) / s, (R.m[2] + R.m[6]) / s, (R.m[5] + R.m[7]) / s, 0.25f * s);
  }
  return q;
}

// The Gaussians that follow particles, for one view: mean = the particle's
// position in the world; covariance F Sigma F^T (F taken to the world frame,
// A^T F A: the world -> box map is a rotation A and a uniform scale, which
// cancels), written back as a rotation and scales through the SVD of
// F R diag(s); colour = the SH at the view direction turned back by the
// rotation part of F (the coefficients stay as trained), baked into the DC
// coefficient with the other coefficients zero, so that the renderer's
// degree-0 evaluation gives exactly that colour.
__kernel void mpm_gaussians(int n, int K, int K_active,
                            __global const int* particle,    // [n] the particle each Gaussian follows
                            __global const float* x,         // [N,3] particle positions in the box
                            __global const float* F,         // [N,9]
                            __constant const float* frame,   // [16] A (9, world -> box), scale, world origin (3), box origin (3)
                            float4 campos,                   // camera centre (world)
                            __global const float* scales0,   // [n,3] trained scales
                            __global const float* quats0,    // [n,4] trained rotations (w x y z)
                            __global const float* sh0,       // [n,K,3] trained SH
                            __global float* means,           // [n,3] out
                            __global float* scales,          // [n,3] out
                            __global float* quats,           // [n,4] out
                            __global float* sh) {            // [n,K,3] out: DC baked, the rest 0
  const int g = get_global_id(0);
  if (g >= n) return;
  const int p = particle[g];
  mat3 A;
  for (int i = 0; i < 9; ++i) A.m[i] = frame[i];
  const float s = frame[9];
  const float3 o = (float3)(frame[10], frame[11], frame[12]), b = (float3)(frame[13], frame[14], frame[15]);
  const mat3 At = mat3_transpose(A);
  const float3 mean = mat3_vec(At, (vload3(p, x) - b) / s) + o;
  const mat3 Fw = mat3_mul(At, mat3_mul(mat3_load_g(F + 9 * p), A));
  // F R diag(s) = U diag(sig) V^T  =>  F Sigma F^T = U diag(sig^2) U^T.
  const float4 q0 = vload4(g, quats0);
  const float qn = length(q0);
  const mat3 R0 = quat_to_rotmat(qn > 0.f ? q0 / qn : (float4)(1.f, 0.f, 0.f, 0.f));
  const float3 s0 = vload3(g, scales0);
  mat3 M = mat3_mul(Fw, R0);
  for (int i = 0; i < 3; ++i) {
    M.m[3 * i] *= s0.x;
    M.m[3 * i + 1] *= s0.y;
    M.m[3 * i + 2] *= s0.z;
  }
  mat3 U, V, Uf, Vf;
  float3 sig, sigf;
  svd3(M, &U, &sig, &V);
  vstore3(mean, g, means);
  vstore3(fmax(fabs(sig), (float3)(1e-9f)), g, scales);
  vstore4(rotmat_to_quat(U), g, quats);
  // The view direction in the Gaussian's rest frame: R_F^T d, R_F = U_F V_F^T.
  svd3(Fw, &Uf, &sigf, &Vf);
  const mat3 RF = mat3_mul(Uf, mat3_transpose(Vf));
  float inv_norm;
  const float3 d = mat3_vec(mat3_transpose(RF), view_dir(mean, campos.xyz, &inv_norm));
  float3 rgb = (float3)(0.f);
  for (int k = 0; k < K_active; ++k) {
    float3 grad;
    rgb += sh_basis(k, d, &grad) * vload3(g * K + k, sh0);
  }
  vstore3(rgb / SH_C0, g * K, sh);
  for (int k = 1; k < K; ++k) vstore3((float3)(0.f), g * K + k, sh);
}
