// Fused EWA projection + SH colour on the CPU, forward and hand-written backward.
//
// Built and loaded like raster.cpp (plain C ABI, ctypes, no torch headers). Semantics are
// those of splat_train/render/projection.py (project_gaussians) and splat_train/render/sh.py (sh_to_color),
// which stay the reference: the per-Gaussian maths runs in double whatever the tensor dtype,
// as the torch code does, and the gradients are those autograd gives for that code (the 1.3 x
// field-of-view clamp of the Jacobian passes no gradient to x / z where it is active; culled
// Gaussians get zero gradients; the colour clamp at 0 passes none where it is active).
//
// Camera block cam[21] (double): R (row-major 3x3, world -> camera), t (3), fx, fy, cx, cy,
// near, eps2d, camera centre in world (3), width, height. One thread per chunk of 1024
// Gaussians from a shared counter; every Gaussian is independent, so results do not depend on
// the thread count.
//
// Vectorised across Gaussians: blocks of LN = 8 Gaussians run the same double-precision code
// with one Gaussian per lane (GCC/Clang vector extensions: one zmm register with AVX-512, two
// ymm with AVX2, four xmm or scalar code elsewhere). Branches are per-lane selects, so every
// lane computes exactly what the scalar per-Gaussian code did (same operations, same order);
// the inputs are transposed into the lanes and the results back (a partial last block pads its
// lanes with a harmless Gaussian and writes only the real ones). That made the forward
// ~12 -> ~5 ms and the backward ~20 -> ~9.5 ms at 100k Gaussians (SH degree 3, one core; the
// SH part, ~2.5 + ~6.5 ms, is mostly moving 48 coefficients per Gaussian in and out of lanes:
// AVX2 gathers and an in-register 8x8 transpose were both tried and were not faster; so were,
// on this AMD EPYC (Zen 4, AVX-512), 8x8 double transposes in zmm registers (masked float
// loads / stores, 24 shuffles per 8 coefficients) for the rest coefficients' load and the
// gradient's store, and software prefetch of the next blocks' SH rows: 206k Gaussians, one
// thread, forward / backward 10.0 / 21.2 ms as here, 11.0 / 21.8 (load) and 11.1 / 22.5 ms
// (load + store), the same binaries timed in one process). What did pay, with AVX-512VL, for
// float32 rows of degree 3 in full blocks (load_sh16_block / store_sh16_block): transposing in
// float, 8 x 8 in ymm registers, with the conversion to or from double done on whole vectors,
// and AVX-512 mask registers for the partial rows (with AVX2's vmaskmovps stores instead, the
// projection backward measured 3.5-6 ms slower on this CPU, two rounds). 201k-Gaussian fern
// checkpoint, one thread, CPU ms, three alternating rounds: forward 9.75-9.89 -> 8.70-8.73,
// backward (with the test loss's autograd) 33.6-34.5 -> 31.2-31.7; bit-identical.
//
// The SH coefficients come as a DC pointer and a rest pointer with row strides, so the
// trainer's sh_dc [N, 3] and sh_rest [N, 15, 3] parameters are read (and their gradients
// written) in place, and one [N, K, 3] tensor is the special case rest = dc + 3.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#if defined(__AVX2__) || defined(__AVX512F__) || defined(__SSE2__)
#include <immintrin.h>
#endif

#include "vec8d.h"

namespace {

constexpr double C0 = 0.28209479177387814;
constexpr double C1 = 0.4886025119029199;
constexpr double C2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                          -1.0925484305920792, 0.5462742152960396};
constexpr double C3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
                          0.3731763325901154, -0.4570457994644658, 1.445305721320277,
                          -0.5900435899266435};
constexpr int64_t CHUNK = 1024;

using namespace vec8d;  // D, Mk, LN (Gaussians per vector), bc, vmax, vmin, vsqrt, vfloor, vceil

inline Mk isfin(D x) { return (x - x) == bc(0.0); }  // false for inf and NaN

struct Cam {
  double R[9], t[3], fx, fy, cx, cy, near, eps2d, cc[3];
  int64_t W, H;
  double lxp, lxn, lyp, lyn;
  explicit Cam(const double* c) {
    for (int i = 0; i < 9; ++i) R[i] = c[i];
    for (int i = 0; i < 3; ++i) t[i] = c[9 + i];
    fx = c[12]; fy = c[13]; cx = c[14]; cy = c[15]; near = c[16]; eps2d = c[17];
    for (int i = 0; i < 3; ++i) cc[i] = c[18 + i];
    W = (int64_t)c[21]; H = (int64_t)c[22];
    const double tfx = 0.5 * (double)W / fx, tfy = 0.5 * (double)H / fy;
    lxp = ((double)W - cx) / fx + 0.3 * tfx;
    lxn = cx / fx + 0.3 * tfx;
    lyp = ((double)H - cy) / fy + 0.3 * tfy;
    lyn = cy / fy + 0.3 * tfy;
  }
};

// One block of LN Gaussians, transposed into lanes (double), with everything the forward
// computes that the backward reuses.
struct Block {
  int nl;               // real lanes (the rest are padding)
  D m[3], q0[4], s[3];  // inputs
  D p[3];               // camera-frame mean
  D zs;                 // z, or 1 when behind the near plane
  Mk ok;
  D u, v;
  D tx, ty;             // Jacobian evaluation point (clamped)
  Mk clx, cly;          // clamp active
  D J0, J2, J4, J5;     // the non-zero entries of the 2x3 Jacobian
  D q[4];               // normalised quaternion (w, x, y, z)
  D qn;                 // max(|q|, 1e-12)
  D Rq[9];              // rotation of the Gaussian
  D M[9];               // Rq diag(s)
  D Sig[9];             // world covariance
  D T[6];               // J R
  D a, b, c;            // dilated 2D covariance
  D det;
};

// Lane l of the block starting at entry i0 holds Gaussian i0 + l, or idx[i0 + l] with a list of
// Gaussian indices idx (the camera-only backward's Gaussians with a non-zero cotangent).
inline int64_t row(const int64_t* idx, int64_t k) { return idx != nullptr ? idx[k] : k; }

template <typename T>
inline void load_block(int64_t i0, int64_t n, const T* means, const T* quats, const T* scales, Block& B,
                       const int64_t* idx = nullptr) {
  B.nl = (int)std::min<int64_t>(LN, n - i0);
  for (int l = 0; l < LN; ++l) {
    const bool real = l < B.nl;
    const int64_t i = row(idx, i0 + (real ? l : 0));
    for (int k = 0; k < 3; ++k) B.m[k][l] = (double)means[3 * i + k];
    for (int k = 0; k < 4; ++k) B.q0[k][l] = (double)quats[4 * i + k];
    for (int k = 0; k < 3; ++k) B.s[k][l] = (double)scales[3 * i + k];
  }
}

// The per-Gaussian projection (splat_train/render/projection.py), lane-wise.
inline void project_block(const Cam& cam, Block& P) {
  for (int r = 0; r < 3; ++r)
    P.p[r] = cam.R[3 * r] * P.m[0] + cam.R[3 * r + 1] * P.m[1] + cam.R[3 * r + 2] * P.m[2] + cam.t[r];
  const D z = P.p[2];
  const Mk in_front = z >= bc(cam.near);
  P.zs = in_front ? z : bc(1.0);
  const D x = P.p[0], y = P.p[1], zs = P.zs;
  P.u = cam.fx * x / zs + cam.cx;
  P.v = cam.fy * y / zs + cam.cy;
  const D xz = x / zs, yz = y / zs;
  const D cxz = vmin(vmax(xz, bc(-cam.lxn)), bc(cam.lxp));
  const D cyz = vmin(vmax(yz, bc(-cam.lyn)), bc(cam.lyp));
  P.clx = cxz != xz;
  P.cly = cyz != yz;
  P.tx = zs * cxz;
  P.ty = zs * cyz;
  P.J0 = cam.fx / zs; P.J2 = -cam.fx * P.tx / (zs * zs);
  P.J4 = cam.fy / zs; P.J5 = -cam.fy * P.ty / (zs * zs);
  const D* q0 = P.q0;
  const D nrm = vsqrt(q0[0] * q0[0] + q0[1] * q0[1] + q0[2] * q0[2] + q0[3] * q0[3]);
  P.qn = vmax(nrm, bc(1e-12));
  for (int i = 0; i < 4; ++i) P.q[i] = q0[i] / P.qn;
  const D w = P.q[0], qx = P.q[1], qy = P.q[2], qz = P.q[3];
  D* R = P.Rq;
  R[0] = 1 - 2 * (qy * qy + qz * qz); R[1] = 2 * (qx * qy - w * qz); R[2] = 2 * (qx * qz + w * qy);
  R[3] = 2 * (qx * qy + w * qz); R[4] = 1 - 2 * (qx * qx + qz * qz); R[5] = 2 * (qy * qz - w * qx);
  R[6] = 2 * (qx * qz - w * qy); R[7] = 2 * (qy * qz + w * qx); R[8] = 1 - 2 * (qx * qx + qy * qy);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) P.M[3 * i + j] = R[3 * i + j] * P.s[j];
  for (int i = 0; i < 3; ++i)
    for (int j = i; j < 3; ++j) {
      P.Sig[3 * i + j] = P.M[3 * i] * P.M[3 * j] + P.M[3 * i + 1] * P.M[3 * j + 1] + P.M[3 * i + 2] * P.M[3 * j + 2];
      P.Sig[3 * j + i] = P.Sig[3 * i + j];
    }
  // T = J R with J = [[J0, 0, J2], [0, J4, J5]]
  for (int j = 0; j < 3; ++j) {
    P.T[j] = P.J0 * cam.R[j] + P.J2 * cam.R[6 + j];
    P.T[3 + j] = P.J4 * cam.R[3 + j] + P.J5 * cam.R[6 + j];
  }
  D TS[6];  // T Sig
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      TS[3 * i + j] = P.T[3 * i] * P.Sig[j] + P.T[3 * i + 1] * P.Sig[3 + j] + P.T[3 * i + 2] * P.Sig[6 + j];
  const D c00 = TS[0] * P.T[0] + TS[1] * P.T[1] + TS[2] * P.T[2];
  const D c01 = TS[0] * P.T[3] + TS[1] * P.T[4] + TS[2] * P.T[5];
  const D c11 = TS[3] * P.T[3] + TS[4] * P.T[4] + TS[5] * P.T[5];
  P.a = c00 + cam.eps2d;
  P.b = c01;
  P.c = c11 + cam.eps2d;
  P.det = P.a * P.c - P.b * P.b;
  P.ok = in_front & isfin(P.det) & (P.det > bc(0.0)) & isfin(P.u) & isfin(P.v);
}

// Real SH basis values b[16] for unit directions d (3DGS order and signs, see sh.py).
inline void sh_basis(int deg, const D* d, D* b) {
  const D x = d[0], y = d[1], z = d[2];
  b[0] = bc(C0);
  if (deg < 1) return;
  b[1] = -C1 * y; b[2] = C1 * z; b[3] = -C1 * x;
  if (deg < 2) return;
  const D xx = x * x, yy = y * y, zz = z * z;
  b[4] = C2[0] * x * y; b[5] = C2[1] * y * z; b[6] = C2[2] * (2 * zz - xx - yy);
  b[7] = C2[3] * x * z; b[8] = C2[4] * (xx - yy);
  if (deg < 3) return;
  b[9] = C3[0] * y * (3 * xx - yy); b[10] = C3[1] * x * y * z;
  b[11] = C3[2] * y * (4 * zz - xx - yy); b[12] = C3[3] * z * (2 * zz - 3 * xx - 3 * yy);
  b[13] = C3[4] * x * (4 * zz - xx - yy); b[14] = C3[5] * z * (xx - yy);
  b[15] = C3[6] * x * (xx - 3 * yy);
}

// vd[axis] += s[k] * d/d(axis) basis_k for k = 1 .. nb - 1 (the non-zero entries of the
// basis gradient, k in order, axes x, y, z; a zero entry adds nothing).
inline void sh_grad_dot(int deg, const D* d, const D* s, D* vd) {
  const D x = d[0], y = d[1], z = d[2];
  if (deg < 1) return;
  vd[1] += s[1] * -C1; vd[2] += s[2] * C1; vd[0] += s[3] * -C1;
  if (deg < 2) return;
  const D xx = x * x, yy = y * y, zz = z * z;
  vd[0] += s[4] * (C2[0] * y); vd[1] += s[4] * (C2[0] * x);
  vd[1] += s[5] * (C2[1] * z); vd[2] += s[5] * (C2[1] * y);
  vd[0] += s[6] * (C2[2] * -2 * x); vd[1] += s[6] * (C2[2] * -2 * y); vd[2] += s[6] * (C2[2] * 4 * z);
  vd[0] += s[7] * (C2[3] * z); vd[2] += s[7] * (C2[3] * x);
  vd[0] += s[8] * (C2[4] * 2 * x); vd[1] += s[8] * (C2[4] * -2 * y);
  if (deg < 3) return;
  vd[0] += s[9] * (C3[0] * 6 * x * y); vd[1] += s[9] * (C3[0] * (3 * xx - 3 * yy));
  vd[0] += s[10] * (C3[1] * y * z); vd[1] += s[10] * (C3[1] * x * z); vd[2] += s[10] * (C3[1] * x * y);
  vd[0] += s[11] * (C3[2] * -2 * x * y); vd[1] += s[11] * (C3[2] * (4 * zz - xx - 3 * yy));
  vd[2] += s[11] * (C3[2] * 8 * y * z);
  vd[0] += s[12] * (C3[3] * -6 * x * z); vd[1] += s[12] * (C3[3] * -6 * y * z);
  vd[2] += s[12] * (C3[3] * (6 * zz - 3 * xx - 3 * yy));
  vd[0] += s[13] * (C3[4] * (4 * zz - 3 * xx - yy)); vd[1] += s[13] * (C3[4] * -2 * x * y);
  vd[2] += s[13] * (C3[4] * 8 * x * z);
  vd[0] += s[14] * (C3[5] * 2 * x * z); vd[1] += s[14] * (C3[5] * -2 * y * z); vd[2] += s[14] * (C3[5] * (xx - yy));
  vd[0] += s[15] * (C3[6] * (3 * xx - 3 * yy)); vd[1] += s[15] * (C3[6] * -6 * x * y);
}

inline void view_dir(const Cam& cam, const D* m, D* d, D& norm) {
  const D v[3] = {m[0] - cam.cc[0], m[1] - cam.cc[1], m[2] - cam.cc[2]};
  norm = vsqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
  const Mk far = norm > bc(1e-12);
  const D den = vmax(norm, bc(1e-12));
  for (int i = 0; i < 3; ++i) d[i] = far ? v[i] / den : bc(0.0);
}

// Where the SH coefficients of Gaussian i live: the DC term (3 values) at dc + i * dc_stride,
// coefficients 1 .. rest_k at rest + i * rest_stride (3 per coefficient). One [N, K, 3] tensor
// is dc = sh, rest = sh + 3, both strides 3 K, rest_k = K - 1; separate [N, 3] and
// [N, K - 1, 3] tensors (the trainer's sh_dc / sh_rest parameters) need no concatenation.
template <typename T>
struct SH {
  const T* dc;
  int64_t dc_stride;
  const T* rest;
  int64_t rest_stride, rest_k;
};

// The first nb SH coefficients of the block's Gaussians, transposed: co[3 k + ch][lane].
template <int NB, typename T>
inline void load_sh_n(const Block& B, int64_t i0, int nb, const SH<T>& sh, D* co, const int64_t* idx) {
  const int nr = NB > 0 ? 3 * (NB - 1) : 3 * (nb - 1);
  for (int l = 0; l < LN; ++l) {
    const int64_t i = row(idx, i0 + (l < B.nl ? l : 0));
    const T* dc = sh.dc + i * sh.dc_stride;
    const T* src = sh.rest + i * sh.rest_stride;
    for (int j = 0; j < 3; ++j) co[j][l] = (double)dc[j];
    for (int j = 0; j < nr; ++j) co[3 + j][l] = (double)src[j];
  }
}
#if defined(__AVX512VL__)
// 8 x 8 float transpose: r[j] = coefficient j's 8 lanes in, r[l] = lane l's 8 coefficients out.
inline void transpose8(__m256* r) {
  const __m256 t0 = _mm256_unpacklo_ps(r[0], r[1]), t1 = _mm256_unpackhi_ps(r[0], r[1]);
  const __m256 t2 = _mm256_unpacklo_ps(r[2], r[3]), t3 = _mm256_unpackhi_ps(r[2], r[3]);
  const __m256 t4 = _mm256_unpacklo_ps(r[4], r[5]), t5 = _mm256_unpackhi_ps(r[4], r[5]);
  const __m256 t6 = _mm256_unpacklo_ps(r[6], r[7]), t7 = _mm256_unpackhi_ps(r[6], r[7]);
  const __m256 s0 = _mm256_shuffle_ps(t0, t2, 0x44), s1 = _mm256_shuffle_ps(t0, t2, 0xEE);
  const __m256 s2 = _mm256_shuffle_ps(t1, t3, 0x44), s3 = _mm256_shuffle_ps(t1, t3, 0xEE);
  const __m256 s4 = _mm256_shuffle_ps(t4, t6, 0x44), s5 = _mm256_shuffle_ps(t4, t6, 0xEE);
  const __m256 s6 = _mm256_shuffle_ps(t5, t7, 0x44), s7 = _mm256_shuffle_ps(t5, t7, 0xEE);
  r[0] = _mm256_permute2f128_ps(s0, s4, 0x20); r[1] = _mm256_permute2f128_ps(s1, s5, 0x20);
  r[2] = _mm256_permute2f128_ps(s2, s6, 0x20); r[3] = _mm256_permute2f128_ps(s3, s7, 0x20);
  r[4] = _mm256_permute2f128_ps(s0, s4, 0x31); r[5] = _mm256_permute2f128_ps(s1, s5, 0x31);
  r[6] = _mm256_permute2f128_ps(s2, s6, 0x31); r[7] = _mm256_permute2f128_ps(s3, s7, 0x31);
}

// load_sh_n<16> for a full block of float rows with rest_k = 15: per Gaussian one 8-float row
// of the DC term and rest 0-4 (masked loads) and five of rest 5-44, six 8 x 8 transposes, then
// each coefficient's lanes widened to double (exact, as the per-lane casts), instead of 48
// scalar loads and conversions per Gaussian.
inline void load_sh16_block(const float* dc, int64_t dc_stride, const float* rest, int64_t rest_stride, D* co) {
  __m256 g[6][8];
  const __m256i shift3 = _mm256_setr_epi32(0, 0, 0, 0, 1, 2, 3, 4);
  for (int l = 0; l < LN; ++l) {
    const float* d = dc + l * dc_stride;
    const float* r = rest + l * rest_stride;
    const __m256 vd = _mm256_maskz_loadu_ps(0x07, d);
    const __m256 vr = _mm256_permutevar8x32_ps(_mm256_maskz_loadu_ps(0x1F, r), shift3);
    g[0][l] = _mm256_blend_ps(vd, vr, 0xF8);
    for (int q = 1; q < 6; ++q) g[q][l] = _mm256_loadu_ps(r + 8 * q - 3);
  }
  for (int q = 0; q < 6; ++q) transpose8(g[q]);
  for (int j = 0; j < 48; ++j) {
    // (masked: the unmasked form trips -Wmaybe-uninitialized in GCC 12's header)
    const __m512d w = _mm512_maskz_cvtps_pd(0xFF, g[j / 8][j % 8]);
    std::memcpy(&co[j], &w, 64);
  }
}
#endif

// Whether the block's SH rows take the transposed paths (load_sh16_block, store_sh16_block):
// AVX-512VL, float rows of degree 3 stored with exactly 15 rest coefficients, a full block.
template <typename T>
inline bool sh16_block(const Block& B, int nb, const SH<T>& sh) {
#if defined(__AVX512VL__)
  return sizeof(T) == 4 && nb == 16 && sh.rest_k == 15 && B.nl == LN;
#else
  return false;
#endif
}

template <typename T>
inline void load_sh(const Block& B, int64_t i0, int nb, const SH<T>& sh, D* co, const int64_t* idx = nullptr) {
#if defined(__AVX512VL__)
  if constexpr (sizeof(T) == 4) {
    if (idx == nullptr && sh16_block(B, nb, sh)) {
      load_sh16_block(sh.dc + i0 * sh.dc_stride, sh.dc_stride, sh.rest + i0 * sh.rest_stride,
                      sh.rest_stride, co);
      return;
    }
  }
#endif
  if (nb == 16) load_sh_n<16>(B, i0, nb, sh, co, idx);  // degree 3: constant trip counts
  else load_sh_n<0>(B, i0, nb, sh, co, idx);
}

template <typename T>
void forward_impl(int64_t n, const double* camp, const T* means, const T* quats, const T* scales,
                  int64_t sh_deg, const SH<T> sh, int64_t tile, T* means2d, T* conics,
                  T* cov2d, T* feat, int32_t* radii, int64_t* rect, uint8_t* visible, int64_t* next) {
  const Cam cam(camp);
  const int64_t gx = (cam.W + tile - 1) / tile, gy = (cam.H + tile - 1) / tile;
  const int nb = sh_deg >= 0 ? (int)((sh_deg + 1) * (sh_deg + 1)) : 0;
  for (int64_t ch; (ch = __atomic_fetch_add(next, 1, __ATOMIC_RELAXED)) * CHUNK < n;) {
    const int64_t i1 = std::min(n, (ch + 1) * CHUNK);
    for (int64_t ib = ch * CHUNK; ib < i1; ib += LN) {
      Block P;
      load_block(ib, n, means, quats, scales, P);
      project_block(cam, P);
      const Mk ok = P.ok;
      const D a = ok ? P.a : bc(1.0), b = ok ? P.b : bc(0.0), c = ok ? P.c : bc(1.0);
      const D det = a * c - b * b;
      const D co0 = c / det, co1 = -b / det, co2 = a / det;
      const D mid = 0.5 * (a + c);
      const D lam = mid + vsqrt(vmax(mid * mid - det, bc(0.1)));
      const D radius = vceil(3.0 * vsqrt(lam));
      const D u = ok ? P.u : bc(0.0), v = ok ? P.v : bc(0.0), zd = ok ? P.p[2] : bc(0.0);
      const D px = u - 0.5, py = v - 0.5;
      const double dt = (double)tile;
      auto cl = [&](D val, int64_t hi) {
        const D f = vfloor(vmin(vmax(val, bc(-1.0)), bc(1e9)));
        return vmin(vmax(f, bc(0.0)), bc((double)hi));
      };
      const D rr[4] = {cl((px - radius) / dt, gx), cl((px + radius + (dt - 1)) / dt, gx),
                       cl((py - radius) / dt, gy), cl((py + radius + (dt - 1)) / dt, gy)};
      D col[3];
      if (sh_deg >= 0) {
        D d[3], norm, basis[16], co[48];
        view_dir(cam, P.m, d, norm);
        sh_basis((int)sh_deg, d, basis);
        load_sh(P, ib, nb, sh, co);
        for (int ch3 = 0; ch3 < 3; ++ch3) {
          D s = bc(0.0);
          for (int k = 0; k < nb; ++k) s += basis[k] * co[3 * k + ch3];
          col[ch3] = vmax(s + 0.5, bc(0.0));
        }
      }
      for (int l = 0; l < P.nl; ++l) {
        const int64_t i = ib + l;
        conics[3 * i] = (T)co0[l]; conics[3 * i + 1] = (T)co1[l]; conics[3 * i + 2] = (T)co2[l];
        cov2d[3 * i] = (T)a[l]; cov2d[3 * i + 1] = (T)b[l]; cov2d[3 * i + 2] = (T)c[l];
        int64_t r[4];
        for (int k = 0; k < 4; ++k) r[k] = (int64_t)rr[k][l];
        const bool vis = ok[l] && (r[1] - r[0]) * (r[3] - r[2]) > 0;
        visible[i] = vis;
        radii[i] = vis ? (int32_t)std::min(radius[l], 1073741824.0) : 0;
        for (int k = 0; k < 4; ++k) rect[4 * i + k] = vis ? r[k] : 0;
        means2d[2 * i] = (T)u[l];
        means2d[2 * i + 1] = (T)v[l];
        for (int ch3 = 0; ch3 < 3; ++ch3) feat[4 * i + ch3] = sh_deg >= 0 ? (T)col[ch3][l] : T(0);
        feat[4 * i + 3] = (T)zd[l];
      }
    }
  }
}

// Lane l of the coefficient gradients vco into its rows: dc[0..2], rest[0 .. 3 rest_k - 1]
// (zeros past coefficient nb - 1). NB > 0: nb == NB (constant trip counts).
template <int NB, typename T>
inline void store_sh_n(const D* vco, int l, int nb, T* dc, T* rest, int64_t rest_k) {
  const int nr = NB > 0 ? 3 * (NB - 1) : 3 * (nb - 1);
  for (int j = 0; j < 3; ++j) dc[j] = (T)vco[j][l];
  for (int j = 0; j < nr; ++j) rest[j] = (T)vco[3 + j][l];
  for (int64_t j = nr; j < 3 * rest_k; ++j) rest[j] = T(0);
}

#if defined(__AVX512VL__)
// store_sh_n<16> for all eight lanes of a full block, float rows with rest_k = 15: each
// gradient converted to float in its lanes (the same rounding as the per-lane (T) casts), then
// six 8 x 8 transposes and per Gaussian one 3-float and five 8-float stores plus a 5-float one,
// instead of 48 scalar conversions and stores per Gaussian.
inline void store_sh16_block(const D* vco, float* dc, int64_t dc_stride, float* rest, int64_t rest_stride) {
  typedef float F8 __attribute__((vector_size(32)));
  __m256 g[6][8];
  for (int j = 0; j < 48; ++j) {
    const F8 f = __builtin_convertvector(vco[j], F8);
    std::memcpy(&g[j / 8][j % 8], &f, 32);
  }
  for (int q = 0; q < 6; ++q) transpose8(g[q]);
  const __m256i shift3 = _mm256_setr_epi32(3, 4, 5, 6, 7, 0, 0, 0);
  for (int l = 0; l < LN; ++l) {
    float* d = dc + l * dc_stride;
    float* r = rest + l * rest_stride;
    _mm256_mask_storeu_ps(d, 0x07, g[0][l]);  // values 0-2: the DC term
    _mm256_mask_storeu_ps(r, 0x1F, _mm256_permutevar8x32_ps(g[0][l], shift3));  // 3-7: rest 0-4
    for (int q = 1; q < 6; ++q) _mm256_storeu_ps(r + 8 * q - 3, g[q][l]);  // rest 8q-3 .. 8q+4
  }
}
#endif

// The coefficient gradients vco of the block's real lanes into v_dc / v_rest (the layout of sh).
template <typename T>
inline void store_sh(const D* vco, const Block& B, int64_t i0, int nb, const SH<T>& sh, T* v_dc, T* v_rest) {
#if defined(__AVX512VL__)
  if constexpr (sizeof(T) == 4) {
    if (sh16_block(B, nb, sh)) {
      store_sh16_block(vco, v_dc + i0 * sh.dc_stride, sh.dc_stride, v_rest + i0 * sh.rest_stride, sh.rest_stride);
      return;
    }
  }
#endif
  for (int l = 0; l < B.nl; ++l) {
    const int64_t i = i0 + l;
    if (nb == 16) store_sh_n<16>(vco, l, nb, v_dc + i * sh.dc_stride, v_rest + i * sh.rest_stride, sh.rest_k);
    else store_sh_n<0>(vco, l, nb, v_dc + i * sh.dc_stride, v_rest + i * sh.rest_stride, sh.rest_k);
  }
}

// GAUSS: the Gaussians' gradients (v_means .. v_rest), else the camera's alone (v_cam), over the
// n Gaussians listed in idx (every other Gaussian's cotangent rows must be zero: it would add
// nothing); a compile-time flag, so that the camera-only pass carries none of the quaternion,
// scale and SH-coefficient chains.
template <typename T, bool GAUSS>
void backward_impl(int64_t n, const int64_t* idx, const double* camp, const T* means, const T* quats, const T* scales,
                   int64_t sh_deg, const SH<T> sh, const T* v_means2d, int64_t sm, const T* v_conics,
                   int64_t sc, const T* v_feat, int64_t sf, T* v_means, T* v_quats, T* v_scales,
                   T* v_dc, T* v_rest, double* v_cam, int64_t* next) {
  const Cam cam(camp);
  const int nb = sh_deg >= 0 ? (int)((sh_deg + 1) * (sh_deg + 1)) : 0;
  D lane;
  for (int l = 0; l < LN; ++l) lane[l] = (double)l;
  for (int64_t ch; (ch = __atomic_fetch_add(next, 1, __ATOMIC_RELAXED)) * CHUNK < n;) {
    const int64_t i1 = std::min(n, (ch + 1) * CHUNK);
    // camera gradient of this chunk, per lane: dL/dR (9, row-major) and dL/dt (3) through the
    // camera-frame means and T = J R; then (3) the sum over Gaussians of dL/d(mean) through the
    // SH view direction (mean - centre), i.e. -dL/d(centre)
    D acc[15];
    for (int k = 0; k < 15; ++k) acc[k] = bc(0.0);
    for (int64_t ib = ch * CHUNK; ib < i1; ib += LN) {
      Block P;
      load_block(ib, n, means, quats, scales, P, idx);
      project_block(cam, P);
      const Mk real = lane < bc((double)P.nl);  // padding lanes repeat a real Gaussian: not summed
      D g0, g1, g2, vu, vv, vdep, vcin[3];
      for (int l = 0; l < LN; ++l) {
        const int64_t i = row(idx, ib + (l < P.nl ? l : 0));
        g0[l] = (double)v_conics[sc * i]; g1[l] = (double)v_conics[sc * i + 1]; g2[l] = (double)v_conics[sc * i + 2];
        vu[l] = (double)v_means2d[sm * i]; vv[l] = (double)v_means2d[sm * i + 1];
        vdep[l] = (double)v_feat[sf * i + 3];
        if (sh_deg >= 0)
          for (int k = 0; k < 3; ++k) vcin[k][l] = (double)v_feat[sf * i + k];
      }
      D vm[3], vq[4], vs[3] = {bc(0.0), bc(0.0), bc(0.0)};
      {
        // conic (c, -b, a) / det -> (a, b, c)
        const D a = P.a, b = P.b, c = P.c, det = P.det, d2 = det * det;
        const D va = g0 * (-c * c / d2) + g1 * (b * c / d2) + g2 * (1 / det - a * c / d2);
        const D vb = g0 * (2 * b * c / d2) + g1 * (-1 / det - 2 * b * b / d2) + g2 * (2 * a * b / d2);
        const D vc = g0 * (1 / det - a * c / d2) + g1 * (a * b / d2) + g2 * (-a * a / d2);
        // cov = T Sig T^T, with b read from cov[0, 1]: symmetric cotangent Vs
        const D Vs[4] = {va, 0.5 * vb, 0.5 * vb, vc};
        D VT[6];  // Vs T (2x3)
        for (int r = 0; r < 2; ++r)
          for (int j = 0; j < 3; ++j) VT[3 * r + j] = Vs[2 * r] * P.T[j] + Vs[2 * r + 1] * P.T[3 + j];
        D vSig[9];  // T^T Vs T
        for (int r = 0; r < 3; ++r)
          for (int j = 0; j < 3; ++j) vSig[3 * r + j] = P.T[r] * VT[j] + P.T[3 + r] * VT[3 + j];
        D vT[6];  // 2 Vs T Sig
        for (int r = 0; r < 2; ++r)
          for (int j = 0; j < 3; ++j)
            vT[3 * r + j] = 2 * (VT[3 * r] * P.Sig[j] + VT[3 * r + 1] * P.Sig[3 + j] + VT[3 * r + 2] * P.Sig[6 + j]);
        D vJ[6];  // vT R^T
        for (int r = 0; r < 2; ++r)
          for (int j = 0; j < 3; ++j)
            vJ[3 * r + j] = vT[3 * r] * cam.R[3 * j] + vT[3 * r + 1] * cam.R[3 * j + 1] + vT[3 * r + 2] * cam.R[3 * j + 2];
        // Sig = M M^T -> vM = 2 vSig M; M = Rq diag(s)
        D vRq[9];
        for (int r = 0; r < 3; ++r)
          for (int j = 0; j < 3; ++j) {
            const D vMrj = 2 * (vSig[3 * r] * P.M[j] + vSig[3 * r + 1] * P.M[3 + j] + vSig[3 * r + 2] * P.M[6 + j]);
            vs[j] += vMrj * P.Rq[3 * r + j];
            vRq[3 * r + j] = vMrj * P.s[j];
          }
        const D w = P.q[0], x = P.q[1], y = P.q[2], z = P.q[3];
        const D* g = vRq;
        D vqn[4];
        vqn[0] = 2 * (x * (g[7] - g[5]) + y * (g[2] - g[6]) + z * (g[3] - g[1]));
        vqn[1] = 2 * (-2 * x * (g[4] + g[8]) + y * (g[1] + g[3]) + z * (g[2] + g[6]) + w * (g[7] - g[5]));
        vqn[2] = 2 * (-2 * y * (g[0] + g[8]) + x * (g[1] + g[3]) + z * (g[5] + g[7]) + w * (g[2] - g[6]));
        vqn[3] = 2 * (-2 * z * (g[0] + g[4]) + x * (g[2] + g[6]) + y * (g[5] + g[7]) + w * (g[3] - g[1]));
        const Mk big = P.qn > bc(1e-12);
        const D dot = vqn[0] * w + vqn[1] * x + vqn[2] * y + vqn[3] * z;
        for (int k = 0; k < 4; ++k) vq[k] = big ? (vqn[k] - P.q[k] * dot) / P.qn : vqn[k] / 1e-12;
        // J (at tx, ty, z) and the projection (u, v, z) -> camera point
        const D zs = P.zs;
        const double fx = cam.fx, fy = cam.fy;
        D vx = vu * fx / zs, vy = vv * fy / zs;
        D vz = -vu * fx * P.p[0] / (zs * zs) - vv * fy * P.p[1] / (zs * zs) + vdep;
        vz += vJ[0] * (-fx / (zs * zs)) + vJ[4] * (-fy / (zs * zs));
        vz += vJ[2] * (2 * fx * P.tx / (zs * zs * zs)) + vJ[5] * (2 * fy * P.ty / (zs * zs * zs));
        const D vtx = vJ[2] * (-fx / (zs * zs)), vty = vJ[5] * (-fy / (zs * zs));
        vz = P.clx ? vz + vtx * (P.tx / zs) : vz;
        vx = P.clx ? vx : vx + vtx;
        vz = P.cly ? vz + vty * (P.ty / zs) : vz;
        vy = P.cly ? vy : vy + vty;
        const D zero = bc(0.0);
        for (int j = 0; j < 3; ++j)
          vm[j] = P.ok ? cam.R[j] * vx + cam.R[3 + j] * vy + cam.R[6 + j] * vz : zero;
        if (v_cam != nullptr) {
          // p = R m + t: dR += g_p m^T, dt += g_p; T = J R: dR[k][j] += sum_r J[r][k] vT[r][j]
          // (J = [[J0, 0, J2], [0, J4, J5]]). Selects, not products with 0: a culled lane's
          // Jacobian or vT may be inf / NaN, and the torch code passes it no gradient.
          const Mk use = P.ok & real;
          const D gp[3] = {vx, vy, vz};
          for (int i = 0; i < 3; ++i) {
            for (int j = 0; j < 3; ++j) acc[3 * i + j] += use ? gp[i] * P.m[j] : zero;
            acc[9 + i] += use ? gp[i] : zero;
          }
          for (int j = 0; j < 3; ++j) {
            acc[j] += use ? P.J0 * vT[j] : zero;
            acc[3 + j] += use ? P.J4 * vT[3 + j] : zero;
            acc[6 + j] += use ? P.J2 * vT[j] + P.J5 * vT[3 + j] : zero;
          }
        }
        for (int k = 0; k < 4; ++k) vq[k] = P.ok ? vq[k] : zero;
        for (int j = 0; j < 3; ++j) vs[j] = P.ok ? vs[j] : zero;
      }
      D vco[48];
      if (sh_deg >= 0) {
        D d[3], norm, basis[16], co[48];
        view_dir(cam, P.m, d, norm);
        sh_basis((int)sh_deg, d, basis);
        load_sh(P, ib, nb, sh, co, idx);
        D vcol[3];
        for (int ch3 = 0; ch3 < 3; ++ch3) {
          D v = bc(0.0);
          for (int k = 0; k < nb; ++k) v += basis[k] * co[3 * k + ch3];
          vcol[ch3] = (v + 0.5 >= bc(0.0)) ? vcin[ch3] : bc(0.0);
        }
        if constexpr (GAUSS)
          for (int k = 0; k < nb; ++k)
            for (int ch3 = 0; ch3 < 3; ++ch3) vco[3 * k + ch3] = basis[k] * vcol[ch3];
        if (sh_deg >= 1) {
          D sk[16], vd[3] = {bc(0.0), bc(0.0), bc(0.0)};
          for (int k = 1; k < nb; ++k)
            sk[k] = co[3 * k] * vcol[0] + co[3 * k + 1] * vcol[1] + co[3 * k + 2] * vcol[2];
          sh_grad_dot((int)sh_deg, d, sk, vd);
          const D dot = vd[0] * d[0] + vd[1] * d[1] + vd[2] * d[2];
          const Mk far = norm > bc(1e-12);
          for (int j = 0; j < 3; ++j) {
            const D vdir = (vd[j] - d[j] * dot) / norm;
            vm[j] = far ? vm[j] + vdir : vm[j];
            if (v_cam != nullptr) acc[12 + j] += (far & real) ? vdir : bc(0.0);
          }
        }
      }
      if constexpr (GAUSS) {
        for (int l = 0; l < P.nl; ++l) {
          const int64_t i = ib + l;
          for (int j = 0; j < 3; ++j) v_means[3 * i + j] = (T)vm[j][l];
          for (int j = 0; j < 4; ++j) v_quats[4 * i + j] = (T)vq[j][l];
          for (int j = 0; j < 3; ++j) v_scales[3 * i + j] = (T)vs[j][l];
        }
        if (sh_deg >= 0) store_sh(vco, P, ib, nb, sh, v_dc, v_rest);
      }
    }
    if (v_cam != nullptr) {
      // this chunk's row of 12: dL/dR (row-major) and dL/dt, lanes summed in order; the centre
      // c = -R^T t adds dL/dt += R vdir and dL/dR[i][j] += t[i] vdir[j] (dL/dc = -vdir). One
      // row per chunk, summed by the caller in chunk order: the thread count changes nothing.
      double s[15];
      for (int k = 0; k < 15; ++k) {
        s[k] = 0.0;
        for (int l = 0; l < LN; ++l) s[k] += acc[k][l];
      }
      double* out = v_cam + 12 * ch;
      for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) out[3 * i + j] = s[3 * i + j] + cam.t[i] * s[12 + j];
        out[9 + i] = s[9 + i] + cam.R[3 * i] * s[12] + cam.R[3 * i + 1] * s[13] + cam.R[3 * i + 2] * s[14];
      }
    }
  }
}

}  // namespace

extern "C" {

// ABI 2: the SH coefficients as DC and rest pointers with row strides (was one [N, K, 3] array).
// ABI 3: colour and depth leave the forward as one [N, 4] feature row (r, g, b, z: the blend's
// input, no concatenation; colour 0 without SH), and the backward reads the cotangents of
// means2d, conics and that row through row strides (sm, sc, sf elements): the blend backward's
// [N, 6 + F] gradient columns are read in place, where torch copied each strided slice.
// ABI 4: the backward's optional camera gradient (v_cam: one row of 12 doubles per chunk of
// CHUNK Gaussians, dL/dR row-major then dL/dt; null skips it); splat_project_camgrad_*: the
// camera gradient alone over a list of Gaussians (the test-pose protocol's frozen model).
int splat_project_abi_version() { return 4; }

#define SPLAT_PROJECT_ENTRIES(T, SFX)                                                                  \
  void splat_project_forward_##SFX(int64_t n, const double* cam, const T* means, const T* quats,       \
                                   const T* scales, int64_t sh_deg, const T* sh_dc, int64_t dc_stride, \
                                   const T* sh_rest, int64_t rest_stride, int64_t rest_k, int64_t tile, \
                                   T* means2d, T* conics, T* cov2d, T* feat, int32_t* radii,            \
                                   int64_t* rect, uint8_t* visible, int64_t* next) {                    \
    const SH<T> sh{sh_dc, dc_stride, sh_rest, rest_stride, rest_k};                                     \
    forward_impl<T>(n, cam, means, quats, scales, sh_deg, sh, tile, means2d, conics, cov2d, feat,       \
                    radii, rect, visible, next);                                                        \
  }                                                                                                     \
  void splat_project_backward_##SFX(int64_t n, const double* cam, const T* means, const T* quats,      \
                                    const T* scales, int64_t sh_deg, const T* sh_dc, int64_t dc_stride, \
                                    const T* sh_rest, int64_t rest_stride, int64_t rest_k,             \
                                    const T* v_means2d, int64_t sm, const T* v_conics, int64_t sc,     \
                                    const T* v_feat, int64_t sf, T* v_means, T* v_quats, T* v_scales,  \
                                    T* v_dc, T* v_rest, double* v_cam, int64_t* next) {                \
    const SH<T> sh{sh_dc, dc_stride, sh_rest, rest_stride, rest_k};                                     \
    backward_impl<T, true>(n, nullptr, cam, means, quats, scales, sh_deg, sh, v_means2d, sm, v_conics, sc, \
                           v_feat, sf, v_means, v_quats, v_scales, v_dc, v_rest, v_cam, next);          \
  }                                                                                                     \
  void splat_project_camgrad_##SFX(int64_t n, const int64_t* idx, const double* cam, const T* means,   \
                                   const T* quats, const T* scales, int64_t sh_deg, const T* sh_dc,     \
                                   int64_t dc_stride, const T* sh_rest, int64_t rest_stride,           \
                                   int64_t rest_k, const T* v_means2d, int64_t sm, const T* v_conics,  \
                                   int64_t sc, const T* v_feat, int64_t sf, double* v_cam,             \
                                   int64_t* next) {                                                    \
    const SH<T> sh{sh_dc, dc_stride, sh_rest, rest_stride, rest_k};                                     \
    backward_impl<T, false>(n, idx, cam, means, quats, scales, sh_deg, sh, v_means2d, sm, v_conics, sc, \
                            v_feat, sf, nullptr, nullptr, nullptr, nullptr, nullptr, v_cam, next);      \
  }

SPLAT_PROJECT_ENTRIES(float, f32)
SPLAT_PROJECT_ENTRIES(double, f64)

}  // extern "C"
