// Fused EWA projection + SH colour on the CPU, forward and hand-written backward (issue 15).
//
// Built and loaded like _cpu_kernel.cpp (plain C ABI, ctypes, no torch headers). Semantics are
// those of splat_train/projection.py (project_gaussians) and splat_train/sh.py (sh_to_color),
// which stay the reference: the per-Gaussian maths runs in double whatever the tensor dtype,
// as the torch code does, and the gradients are those autograd gives for that code (the 1.3 x
// field-of-view clamp of the Jacobian passes no gradient to x / z where it is active; culled
// Gaussians get zero gradients; the colour clamp at 0 passes none where it is active).
//
// Camera block cam[21] (double): R (row-major 3x3, world -> camera), t (3), fx, fy, cx, cy,
// near, eps2d, camera centre in world (3), width, height. One thread per chunk of 1024
// Gaussians from a shared counter; every Gaussian is independent, so results do not depend on
// the thread count.

#include <algorithm>
#include <cmath>
#include <cstdint>

namespace {

constexpr double C0 = 0.28209479177387814;
constexpr double C1 = 0.4886025119029199;
constexpr double C2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                          -1.0925484305920792, 0.5462742152960396};
constexpr double C3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
                          0.3731763325901154, -0.4570457994644658, 1.445305721320277,
                          -0.5900435899266435};
constexpr int64_t CHUNK = 1024;

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

// Everything the forward computes for one Gaussian, kept for the backward.
struct Proj {
  double p[3];      // camera-frame mean
  double zs;        // z, or 1 when behind the near plane
  bool in_front, ok;
  double u, v;
  double tx, ty;    // Jacobian evaluation point (clamped)
  bool clx, cly;    // clamp active
  double J[6];      // 2x3
  double q[4];      // normalised quaternion (w, x, y, z)
  double qn;        // max(|q|, 1e-12)
  double Rq[9];     // rotation of the Gaussian
  double M[9];      // Rq diag(s)
  double Sig[9];    // world covariance
  double T[6];      // J R
  double a, b, c;   // dilated 2D covariance
  double det;
};

template <typename T>
inline void project_one(const Cam& cam, const T* mean, const T* quat, const T* scale, Proj& P) {
  const double m[3] = {(double)mean[0], (double)mean[1], (double)mean[2]};
  for (int r = 0; r < 3; ++r)
    P.p[r] = cam.R[3 * r] * m[0] + cam.R[3 * r + 1] * m[1] + cam.R[3 * r + 2] * m[2] + cam.t[r];
  const double z = P.p[2];
  P.in_front = z >= cam.near;
  P.zs = P.in_front ? z : 1.0;
  const double x = P.p[0], y = P.p[1], zs = P.zs;
  P.u = cam.fx * x / zs + cam.cx;
  P.v = cam.fy * y / zs + cam.cy;
  const double xz = x / zs, yz = y / zs;
  const double cxz = std::min(std::max(xz, -cam.lxn), cam.lxp);
  const double cyz = std::min(std::max(yz, -cam.lyn), cam.lyp);
  P.clx = cxz != xz;
  P.cly = cyz != yz;
  P.tx = zs * cxz;
  P.ty = zs * cyz;
  P.J[0] = cam.fx / zs; P.J[1] = 0; P.J[2] = -cam.fx * P.tx / (zs * zs);
  P.J[3] = 0; P.J[4] = cam.fy / zs; P.J[5] = -cam.fy * P.ty / (zs * zs);
  const double q0[4] = {(double)quat[0], (double)quat[1], (double)quat[2], (double)quat[3]};
  const double nrm = std::sqrt(q0[0] * q0[0] + q0[1] * q0[1] + q0[2] * q0[2] + q0[3] * q0[3]);
  P.qn = std::max(nrm, 1e-12);
  for (int i = 0; i < 4; ++i) P.q[i] = q0[i] / P.qn;
  const double w = P.q[0], qx = P.q[1], qy = P.q[2], qz = P.q[3];
  double* R = P.Rq;
  R[0] = 1 - 2 * (qy * qy + qz * qz); R[1] = 2 * (qx * qy - w * qz); R[2] = 2 * (qx * qz + w * qy);
  R[3] = 2 * (qx * qy + w * qz); R[4] = 1 - 2 * (qx * qx + qz * qz); R[5] = 2 * (qy * qz - w * qx);
  R[6] = 2 * (qx * qz - w * qy); R[7] = 2 * (qy * qz + w * qx); R[8] = 1 - 2 * (qx * qx + qy * qy);
  const double s[3] = {(double)scale[0], (double)scale[1], (double)scale[2]};
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) P.M[3 * i + j] = R[3 * i + j] * s[j];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      P.Sig[3 * i + j] = P.M[3 * i] * P.M[3 * j] + P.M[3 * i + 1] * P.M[3 * j + 1] + P.M[3 * i + 2] * P.M[3 * j + 2];
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      P.T[3 * i + j] = P.J[3 * i] * cam.R[j] + P.J[3 * i + 1] * cam.R[3 + j] + P.J[3 * i + 2] * cam.R[6 + j];
  double TS[6];  // T Sig
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      TS[3 * i + j] = P.T[3 * i] * P.Sig[j] + P.T[3 * i + 1] * P.Sig[3 + j] + P.T[3 * i + 2] * P.Sig[6 + j];
  const double c00 = TS[0] * P.T[0] + TS[1] * P.T[1] + TS[2] * P.T[2];
  const double c01 = TS[0] * P.T[3] + TS[1] * P.T[4] + TS[2] * P.T[5];
  const double c11 = TS[3] * P.T[3] + TS[4] * P.T[4] + TS[5] * P.T[5];
  P.a = c00 + cam.eps2d;
  P.b = c01;
  P.c = c11 + cam.eps2d;
  P.det = P.a * P.c - P.b * P.b;
  P.ok = P.in_front && std::isfinite(P.det) && P.det > 0 && std::isfinite(P.u) && std::isfinite(P.v);
}

// Real SH basis values b[16] for a unit direction d (3DGS order and signs, see sh.py).
inline void sh_basis(int deg, const double* d, double* b) {
  const double x = d[0], y = d[1], z = d[2];
  b[0] = C0;
  if (deg < 1) return;
  b[1] = -C1 * y; b[2] = C1 * z; b[3] = -C1 * x;
  if (deg < 2) return;
  const double xx = x * x, yy = y * y, zz = z * z;
  b[4] = C2[0] * x * y; b[5] = C2[1] * y * z; b[6] = C2[2] * (2 * zz - xx - yy);
  b[7] = C2[3] * x * z; b[8] = C2[4] * (xx - yy);
  if (deg < 3) return;
  b[9] = C3[0] * y * (3 * xx - yy); b[10] = C3[1] * x * y * z;
  b[11] = C3[2] * y * (4 * zz - xx - yy); b[12] = C3[3] * z * (2 * zz - 3 * xx - 3 * yy);
  b[13] = C3[4] * x * (4 * zz - xx - yy); b[14] = C3[5] * z * (xx - yy);
  b[15] = C3[6] * x * (xx - 3 * yy);
}

// d/d(x, y, z) of each basis function: g[3 k + axis].
inline void sh_basis_grad(int deg, const double* d, double* g) {
  const double x = d[0], y = d[1], z = d[2];
  for (int i = 0; i < 48; ++i) g[i] = 0;
  if (deg < 1) return;
  g[3 * 1 + 1] = -C1; g[3 * 2 + 2] = C1; g[3 * 3 + 0] = -C1;
  if (deg < 2) return;
  const double xx = x * x, yy = y * y, zz = z * z;
  g[12] = C2[0] * y; g[13] = C2[0] * x;
  g[16] = C2[1] * z; g[17] = C2[1] * y;
  g[18] = C2[2] * -2 * x; g[19] = C2[2] * -2 * y; g[20] = C2[2] * 4 * z;
  g[21] = C2[3] * z; g[23] = C2[3] * x;
  g[24] = C2[4] * 2 * x; g[25] = C2[4] * -2 * y;
  if (deg < 3) return;
  g[27] = C3[0] * 6 * x * y; g[28] = C3[0] * (3 * xx - 3 * yy);
  g[30] = C3[1] * y * z; g[31] = C3[1] * x * z; g[32] = C3[1] * x * y;
  g[33] = C3[2] * -2 * x * y; g[34] = C3[2] * (4 * zz - xx - 3 * yy); g[35] = C3[2] * 8 * y * z;
  g[36] = C3[3] * -6 * x * z; g[37] = C3[3] * -6 * y * z; g[38] = C3[3] * (6 * zz - 3 * xx - 3 * yy);
  g[39] = C3[4] * (4 * zz - 3 * xx - yy); g[40] = C3[4] * -2 * x * y; g[41] = C3[4] * 8 * x * z;
  g[42] = C3[5] * 2 * x * z; g[43] = C3[5] * -2 * y * z; g[44] = C3[5] * (xx - yy);
  g[45] = C3[6] * (3 * xx - 3 * yy); g[46] = C3[6] * -6 * x * y;
}

inline void view_dir(const Cam& cam, const double* m, double* d, double& norm) {
  double v[3] = {m[0] - cam.cc[0], m[1] - cam.cc[1], m[2] - cam.cc[2]};
  norm = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
  for (int i = 0; i < 3; ++i) d[i] = norm > 1e-12 ? v[i] / std::max(norm, 1e-12) : 0.0;
}

template <typename T>
void forward_impl(int64_t n, const double* camp, const T* means, const T* quats, const T* scales,
                  int64_t sh_deg, int64_t sh_k, const T* sh, int64_t tile, T* means2d, T* conics,
                  T* cov2d, T* depths, int32_t* radii, int64_t* rect, uint8_t* visible, T* colors,
                  int64_t* next) {
  const Cam cam(camp);
  const int64_t gx = (cam.W + tile - 1) / tile, gy = (cam.H + tile - 1) / tile;
  for (int64_t ch; (ch = __atomic_fetch_add(next, 1, __ATOMIC_RELAXED)) * CHUNK < n;) {
    const int64_t i1 = std::min(n, (ch + 1) * CHUNK);
    for (int64_t i = ch * CHUNK; i < i1; ++i) {
      Proj P;
      project_one(cam, means + 3 * i, quats + 4 * i, scales + 3 * i, P);
      const double a = P.ok ? P.a : 1.0, b = P.ok ? P.b : 0.0, c = P.ok ? P.c : 1.0;
      const double det = a * c - b * b;
      conics[3 * i] = (T)(c / det); conics[3 * i + 1] = (T)(-b / det); conics[3 * i + 2] = (T)(a / det);
      cov2d[3 * i] = (T)a; cov2d[3 * i + 1] = (T)b; cov2d[3 * i + 2] = (T)c;
      const double mid = 0.5 * (a + c);
      const double lam = mid + std::sqrt(std::max(mid * mid - det, 0.1));
      const double radius = std::ceil(3.0 * std::sqrt(lam));
      const double px = (P.ok ? P.u : 0.0) - 0.5, py = (P.ok ? P.v : 0.0) - 0.5;
      const double big = 1e9;
      auto cl = [&](double val, int64_t hi) {
        const double f = std::floor(std::min(std::max(val, -1.0), big));
        return (int64_t)std::min(std::max(f, 0.0), (double)hi);
      };
      int64_t r[4] = {cl((px - radius) / tile, gx), cl((px + radius + tile - 1) / tile, gx),
                      cl((py - radius) / tile, gy), cl((py + radius + tile - 1) / tile, gy)};
      const bool vis = P.ok && (r[1] - r[0]) * (r[3] - r[2]) > 0;
      visible[i] = vis;
      radii[i] = vis ? (int32_t)std::min(radius, 1073741824.0) : 0;
      for (int k = 0; k < 4; ++k) rect[4 * i + k] = vis ? r[k] : 0;
      means2d[2 * i] = (T)(P.ok ? P.u : 0.0);
      means2d[2 * i + 1] = (T)(P.ok ? P.v : 0.0);
      depths[i] = (T)(P.ok ? P.p[2] : 0.0);
      if (sh_deg >= 0) {
        const double m[3] = {(double)means[3 * i], (double)means[3 * i + 1], (double)means[3 * i + 2]};
        double d[3], norm, basis[16];
        view_dir(cam, m, d, norm);
        sh_basis((int)sh_deg, d, basis);
        const int nb = (int)((sh_deg + 1) * (sh_deg + 1));
        const T* co = sh + i * sh_k * 3;
        for (int ch3 = 0; ch3 < 3; ++ch3) {
          double v = 0;
          for (int k = 0; k < nb; ++k) v += basis[k] * (double)co[3 * k + ch3];
          colors[3 * i + ch3] = (T)std::max(v + 0.5, 0.0);
        }
      }
    }
  }
}

template <typename T>
void backward_impl(int64_t n, const double* camp, const T* means, const T* quats, const T* scales,
                   int64_t sh_deg, int64_t sh_k, const T* sh, const T* v_means2d, const T* v_conics,
                   const T* v_depths, const T* v_colors, T* v_means, T* v_quats, T* v_scales,
                   T* v_sh, int64_t* next) {
  const Cam cam(camp);
  for (int64_t ch; (ch = __atomic_fetch_add(next, 1, __ATOMIC_RELAXED)) * CHUNK < n;) {
    const int64_t i1 = std::min(n, (ch + 1) * CHUNK);
    for (int64_t i = ch * CHUNK; i < i1; ++i) {
      double vm[3] = {0, 0, 0}, vq[4] = {0, 0, 0, 0}, vs[3] = {0, 0, 0};
      Proj P;
      project_one(cam, means + 3 * i, quats + 4 * i, scales + 3 * i, P);
      if (P.ok) {
        // conic (c, -b, a) / det -> (a, b, c)
        const double a = P.a, b = P.b, c = P.c, det = P.det, d2 = det * det;
        const double g0 = (double)v_conics[3 * i], g1 = (double)v_conics[3 * i + 1], g2 = (double)v_conics[3 * i + 2];
        const double va = g0 * (-c * c / d2) + g1 * (b * c / d2) + g2 * (1 / det - a * c / d2);
        const double vb = g0 * (2 * b * c / d2) + g1 * (-1 / det - 2 * b * b / d2) + g2 * (2 * a * b / d2);
        const double vc = g0 * (1 / det - a * c / d2) + g1 * (a * b / d2) + g2 * (-a * a / d2);
        // cov = T Sig T^T, with b read from cov[0, 1]: symmetric cotangent Vs
        const double Vs[4] = {va, 0.5 * vb, 0.5 * vb, vc};
        double VT[6];  // Vs T (2x3)
        for (int r = 0; r < 2; ++r)
          for (int j = 0; j < 3; ++j) VT[3 * r + j] = Vs[2 * r] * P.T[j] + Vs[2 * r + 1] * P.T[3 + j];
        double vSig[9];  // T^T Vs T
        for (int r = 0; r < 3; ++r)
          for (int j = 0; j < 3; ++j) vSig[3 * r + j] = P.T[r] * VT[j] + P.T[3 + r] * VT[3 + j];
        double vT[6];  // 2 Vs T Sig
        for (int r = 0; r < 2; ++r)
          for (int j = 0; j < 3; ++j)
            vT[3 * r + j] = 2 * (VT[3 * r] * P.Sig[j] + VT[3 * r + 1] * P.Sig[3 + j] + VT[3 * r + 2] * P.Sig[6 + j]);
        double vJ[6];  // vT R^T
        for (int r = 0; r < 2; ++r)
          for (int j = 0; j < 3; ++j)
            vJ[3 * r + j] = vT[3 * r] * cam.R[3 * j] + vT[3 * r + 1] * cam.R[3 * j + 1] + vT[3 * r + 2] * cam.R[3 * j + 2];
        // Sig = M M^T -> vM = 2 vSig M; M = Rq diag(s)
        double vRq[9];
        for (int r = 0; r < 3; ++r)
          for (int j = 0; j < 3; ++j) {
            const double vMrj = 2 * (vSig[3 * r] * P.M[j] + vSig[3 * r + 1] * P.M[3 + j] + vSig[3 * r + 2] * P.M[6 + j]);
            vs[j] += vMrj * P.Rq[3 * r + j];
            vRq[3 * r + j] = vMrj * (double)scales[3 * i + j];
          }
        const double w = P.q[0], x = P.q[1], y = P.q[2], z = P.q[3];
        const double* g = vRq;
        double vqn[4];
        vqn[0] = 2 * (x * (g[7] - g[5]) + y * (g[2] - g[6]) + z * (g[3] - g[1]));
        vqn[1] = 2 * (-2 * x * (g[4] + g[8]) + y * (g[1] + g[3]) + z * (g[2] + g[6]) + w * (g[7] - g[5]));
        vqn[2] = 2 * (-2 * y * (g[0] + g[8]) + x * (g[1] + g[3]) + z * (g[5] + g[7]) + w * (g[2] - g[6]));
        vqn[3] = 2 * (-2 * z * (g[0] + g[4]) + x * (g[2] + g[6]) + y * (g[5] + g[7]) + w * (g[3] - g[1]));
        if (P.qn > 1e-12) {
          const double dot = vqn[0] * w + vqn[1] * x + vqn[2] * y + vqn[3] * z;
          for (int k = 0; k < 4; ++k) vq[k] = (vqn[k] - P.q[k] * dot) / P.qn;
        } else {
          for (int k = 0; k < 4; ++k) vq[k] = vqn[k] / 1e-12;
        }
        // J (at tx, ty, z) and the projection (u, v, z) -> camera point
        const double zs = P.zs, fx = cam.fx, fy = cam.fy;
        const double vu = (double)v_means2d[2 * i], vv = (double)v_means2d[2 * i + 1];
        double vx = vu * fx / zs, vy = vv * fy / zs;
        double vz = -vu * fx * P.p[0] / (zs * zs) - vv * fy * P.p[1] / (zs * zs) + (double)v_depths[i];
        vz += vJ[0] * (-fx / (zs * zs)) + vJ[4] * (-fy / (zs * zs));
        vz += vJ[2] * (2 * fx * P.tx / (zs * zs * zs)) + vJ[5] * (2 * fy * P.ty / (zs * zs * zs));
        const double vtx = vJ[2] * (-fx / (zs * zs)), vty = vJ[5] * (-fy / (zs * zs));
        if (P.clx) vz += vtx * (P.tx / zs); else vx += vtx;
        if (P.cly) vz += vty * (P.ty / zs); else vy += vty;
        const double vp[3] = {vx, vy, vz};
        for (int j = 0; j < 3; ++j) vm[j] = cam.R[j] * vp[0] + cam.R[3 + j] * vp[1] + cam.R[6 + j] * vp[2];
      }
      if (sh_deg >= 0) {
        const double m[3] = {(double)means[3 * i], (double)means[3 * i + 1], (double)means[3 * i + 2]};
        double d[3], norm, basis[16], bg[48];
        view_dir(cam, m, d, norm);
        sh_basis((int)sh_deg, d, basis);
        const int nb = (int)((sh_deg + 1) * (sh_deg + 1));
        const T* co = sh + i * sh_k * 3;
        T* vco = v_sh + i * sh_k * 3;
        double vcol[3];
        for (int ch3 = 0; ch3 < 3; ++ch3) {
          double v = 0;
          for (int k = 0; k < nb; ++k) v += basis[k] * (double)co[3 * k + ch3];
          vcol[ch3] = (v + 0.5 >= 0.0) ? (double)v_colors[3 * i + ch3] : 0.0;
        }
        for (int k = 0; k < sh_k; ++k)
          for (int ch3 = 0; ch3 < 3; ++ch3) vco[3 * k + ch3] = (T)(k < nb ? basis[k] * vcol[ch3] : 0.0);
        if (sh_deg >= 1 && norm > 1e-12) {
          sh_basis_grad((int)sh_deg, d, bg);
          double vd[3] = {0, 0, 0};
          for (int k = 1; k < nb; ++k) {
            const double s = (double)co[3 * k] * vcol[0] + (double)co[3 * k + 1] * vcol[1] + (double)co[3 * k + 2] * vcol[2];
            for (int j = 0; j < 3; ++j) vd[j] += s * bg[3 * k + j];
          }
          const double dot = vd[0] * d[0] + vd[1] * d[1] + vd[2] * d[2];
          for (int j = 0; j < 3; ++j) vm[j] += (vd[j] - d[j] * dot) / norm;
        }
      }
      for (int j = 0; j < 3; ++j) v_means[3 * i + j] = (T)vm[j];
      for (int j = 0; j < 4; ++j) v_quats[4 * i + j] = (T)vq[j];
      for (int j = 0; j < 3; ++j) v_scales[3 * i + j] = (T)vs[j];
    }
  }
}

}  // namespace

extern "C" {

int splat_project_abi_version() { return 1; }

void splat_project_forward_f32(int64_t n, const double* cam, const float* means, const float* quats,
                               const float* scales, int64_t sh_deg, int64_t sh_k, const float* sh,
                               int64_t tile, float* means2d, float* conics, float* cov2d, float* depths,
                               int32_t* radii, int64_t* rect, uint8_t* visible, float* colors, int64_t* next) {
  forward_impl<float>(n, cam, means, quats, scales, sh_deg, sh_k, sh, tile, means2d, conics, cov2d, depths,
                      radii, rect, visible, colors, next);
}
void splat_project_forward_f64(int64_t n, const double* cam, const double* means, const double* quats,
                               const double* scales, int64_t sh_deg, int64_t sh_k, const double* sh,
                               int64_t tile, double* means2d, double* conics, double* cov2d, double* depths,
                               int32_t* radii, int64_t* rect, uint8_t* visible, double* colors, int64_t* next) {
  forward_impl<double>(n, cam, means, quats, scales, sh_deg, sh_k, sh, tile, means2d, conics, cov2d, depths,
                       radii, rect, visible, colors, next);
}
void splat_project_backward_f32(int64_t n, const double* cam, const float* means, const float* quats,
                                const float* scales, int64_t sh_deg, int64_t sh_k, const float* sh,
                                const float* v_means2d, const float* v_conics, const float* v_depths,
                                const float* v_colors, float* v_means, float* v_quats, float* v_scales,
                                float* v_sh, int64_t* next) {
  backward_impl<float>(n, cam, means, quats, scales, sh_deg, sh_k, sh, v_means2d, v_conics, v_depths, v_colors,
                       v_means, v_quats, v_scales, v_sh, next);
}
void splat_project_backward_f64(int64_t n, const double* cam, const double* means, const double* quats,
                                const double* scales, int64_t sh_deg, int64_t sh_k, const double* sh,
                                const double* v_means2d, const double* v_conics, const double* v_depths,
                                const double* v_colors, double* v_means, double* v_quats, double* v_scales,
                                double* v_sh, int64_t* next) {
  backward_impl<double>(n, cam, means, quats, scales, sh_deg, sh_k, sh, v_means2d, v_conics, v_depths, v_colors,
                        v_means, v_quats, v_scales, v_sh, next);
}

}  // extern "C"
