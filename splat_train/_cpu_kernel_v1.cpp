// Tile-based Gaussian alpha blending on the CPU (forward and hand-written backward).
//
// Built by splat_train/_cpu_kernel.py with the system C++ compiler (plain C ABI, called
// through ctypes; no torch headers or OpenMP, so it compiles in about a second anywhere).
// Threads: each caller thread runs the same function with a shared tile counter and takes
// the next tile with an atomic increment (dynamic scheduling; ctypes releases the GIL). Semantics are those of
// splat_train/_reference.py (3DGS forward rules); the backward recomputes the blend back to
// front per pixel as the 3DGS CUDA backward does, but passes no gradient through the 0.99
// clamp where it is active (the exact derivative, matching the autograd reference).
//
// Layout: pixel (row i, col j) has centre (j + 0.5, i + 0.5). Tile t = ty * tiles_x + tx
// covers pixels [16 tx, 16 tx + 16) x [16 ty, 16 ty + 16). Pairs [offsets[t], offsets[t+1])
// hold the Gaussians of tile t in front-to-back order (gauss[k] indexes the N-sized arrays).
//
// Speed-up that keeps the result exact: a pixel outside the ellipse
// d^T conic d <= 2 ln(255 opacity) has alpha < 1/255 and is skipped by the rules anyway, so
// each Gaussian visits only the rows / column spans of that ellipse (with a safety margin)
// inside the tile.

#include <cmath>
#include <cstdint>
#include <cstring>
#include <algorithm>

namespace {

constexpr int TILE = 16;
constexpr int TPIX = TILE * TILE;

template <typename T>
struct Consts {
  static constexpr T alpha_max = T(0.99);
  static constexpr T alpha_min = T(1.0 / 255.0);
  static constexpr T t_min = T(1e-4);
};

// Row span [r0, r1] and, per row, the column span of the ellipse of influence, clipped to the
// tile. Returns false when the Gaussian cannot reach alpha >= 1/255 anywhere.
template <typename T>
struct Footprint {
  bool any;
  T r2;      // squared Mahalanobis radius of the alpha >= 1/255 region (+ margin)
  T a, b, c; // conic
  T mx, my;
};

template <typename T>
inline Footprint<T> make_footprint(T mx, T my, T a, T b, T c, T op) {
  Footprint<T> f;
  f.mx = mx; f.my = my; f.a = a; f.b = b; f.c = c;
  // exp(power) <= 1 for power <= 0, so alpha <= op: below 1/255 nothing is ever blended.
  f.any = !(op < Consts<T>::alpha_min);
  if (!(a > 0) || !(c > 0) || !(a * c - b * b > 0)) {
    f.r2 = -1;  // not positive definite (never after the 0.3 dilation): test every pixel
    return f;
  }
  // alpha = op exp(-q / 2) >= 1/255  <=>  q <= 2 ln(255 op); 1% + 1e-3 margin for rounding.
  const double lim = std::max(255.0 * (double)op, 1.0);
  f.r2 = (T)(2.0 * std::log(lim) * 1.01 + 1e-3);
  return f;
}

// Column range [j0, j1) (tile-local 0..16) for tile-local row y centre py; empty if j0 >= j1.
template <typename T>
inline void row_span(const Footprint<T>& f, T py, T px0, int& j0, int& j1) {
  if (f.r2 < 0) { j0 = 0; j1 = TILE; return; }
  // In double: for thin ellipses the discriminant cancels badly in float.
  const double a = f.a, b = f.b, c = f.c;
  const double dy = (double)f.my - (double)py;
  // q(dx) = a dx^2 + 2 b dx dy + c dy^2 <= r2, dx = mx - px
  const double disc = b * b * dy * dy - a * (c * dy * dy - (double)f.r2);
  if (!(disc >= 0)) { j0 = 0; j1 = 0; return; }
  const double s = std::sqrt(disc);
  const double dx_lo = (-b * dy - s) / a;
  const double dx_hi = (-b * dy + s) / a;
  // px = mx - dx; pixel centre px = px0 + j + 0.5
  const double px_lo = (double)f.mx - dx_hi, px_hi = (double)f.mx - dx_lo;
  double jl = std::ceil(px_lo - (double)px0 - 0.5 - 1e-3);
  double jh = std::floor(px_hi - (double)px0 - 0.5 + 1e-3);
  jl = std::max(jl, 0.0); jh = std::min(jh, double(TILE - 1));
  if (!(jl <= jh)) { j0 = 0; j1 = 0; return; }
  j0 = (int)jl; j1 = (int)jh + 1;
}

// Tile-local rows [i0, i1) that the ellipse q <= r2 can reach: |dy| <= sqrt(r2 a / det).
template <typename T>
inline void row_range(const Footprint<T>& f, T py0, int rows, int& i0, int& i1) {
  if (f.r2 < 0) { i0 = 0; i1 = rows; return; }
  const double a = f.a, b = f.b, c = f.c;
  const double half = std::sqrt((double)f.r2 * a / (a * c - b * b)) + 1e-3;
  // row centre py = py0 + i + 0.5 must satisfy |my - py| <= half
  double lo = std::ceil((double)f.my - half - (double)py0 - 0.5);
  double hi = std::floor((double)f.my + half - (double)py0 - 0.5);
  lo = std::max(lo, 0.0); hi = std::min(hi, double(rows - 1));
  if (!(lo <= hi)) { i0 = 0; i1 = 0; return; }
  i0 = (int)lo; i1 = (int)hi + 1;
}

template <typename T>
void forward_impl(int64_t tiles_x, int64_t tiles_y, int64_t W, int64_t H, int64_t F,
                  const int64_t* offsets, const int64_t* gauss, const T* means2d,
                  const T* conics, const T* opac, const T* feat, T* out_accum, T* out_T,
                  int32_t* out_last, int32_t* out_count, int64_t* next_tile) {
  const int64_t n_tiles = tiles_x * tiles_y;
  for (int64_t t; (t = __atomic_fetch_add(next_tile, 1, __ATOMIC_RELAXED)) < n_tiles;) {
    const int64_t tx = t % tiles_x, ty = t / tiles_x;
    const int64_t x0 = tx * TILE, y0 = ty * TILE;
    const int rows = (int)std::min<int64_t>(TILE, H - y0);
    const int cols = (int)std::min<int64_t>(TILE, W - x0);
    T Tr[TPIX];
    T acc[TPIX * 8];
    T* accp = acc;
    T* heap = nullptr;
    if (F > 8) { heap = new T[TPIX * F]; accp = heap; }
    int32_t last[TPIX];
    int32_t count[TPIX];
    bool done[TPIX];
    int active = 0;
    for (int p = 0; p < TPIX; ++p) {
      int i = p / TILE, j = p % TILE;
      Tr[p] = T(1);
      last[p] = 0;
      count[p] = 0;
      done[p] = !(i < rows && j < cols);
      active += !done[p];
      for (int64_t f = 0; f < F; ++f) accp[p * F + f] = T(0);
    }
    const int64_t k0 = offsets[t], k1 = offsets[t + 1];
    for (int64_t k = k0; k < k1 && active > 0; ++k) {
      const int64_t g = gauss[k];
      const T mx = means2d[2 * g], my = means2d[2 * g + 1];
      const T a = conics[3 * g], b = conics[3 * g + 1], c = conics[3 * g + 2];
      const T op = opac[g];
      Footprint<T> fp = make_footprint(mx, my, a, b, c, op);
      if (!fp.any) continue;
      const T* fg = feat + g * F;
      int i0, i1;
      row_range(fp, T(y0), rows, i0, i1);
      for (int i = i0; i < i1; ++i) {
        const T py = T(y0 + i) + T(0.5);
        int j0, j1;
        row_span(fp, py, T(x0), j0, j1);
        j1 = std::min(j1, cols);
        for (int j = j0; j < j1; ++j) {
          const int p = i * TILE + j;
          if (done[p]) continue;
          const T dx = mx - (T(x0 + j) + T(0.5));
          const T dy = my - py;
          const T power = T(-0.5) * (a * dx * dx + c * dy * dy) - b * dx * dy;
          if (power > T(0)) continue;
          const T alpha = std::min(Consts<T>::alpha_max, op * std::exp(power));
          if (alpha < Consts<T>::alpha_min) continue;
          const T test_T = Tr[p] * (T(1) - alpha);
          if (test_T < Consts<T>::t_min) { done[p] = true; --active; continue; }
          const T w = alpha * Tr[p];
          for (int64_t f = 0; f < F; ++f) accp[p * F + f] += w * fg[f];
          Tr[p] = test_T;
          last[p] = (int32_t)(k - k0 + 1);
          ++count[p];
        }
      }
    }
    for (int i = 0; i < rows; ++i)
      for (int j = 0; j < cols; ++j) {
        const int p = i * TILE + j;
        const int64_t pix = (y0 + i) * W + (x0 + j);
        out_T[pix] = Tr[p];
        out_last[pix] = last[p];
        out_count[pix] = count[p];
        for (int64_t f = 0; f < F; ++f) out_accum[pix * F + f] = accp[p * F + f];
      }
    delete[] heap;
  }
}

// Per pair k the gradient row v_pair[k * (6 + F) + ...] = (v_mx, v_my, v_a, v_b, v_c, v_op,
// v_feat[0..F)). Each pair belongs to one tile, so tiles write disjoint rows (no races).
template <typename T>
void backward_impl(int64_t tiles_x, int64_t tiles_y, int64_t W, int64_t H, int64_t F,
                   const int64_t* offsets, const int64_t* gauss, const T* means2d,
                   const T* conics, const T* opac, const T* feat, const T* out_T,
                   const int32_t* out_last, const T* v_accum, const T* v_T, T* v_pair,
                   int64_t* next_tile) {
  const int64_t n_tiles = tiles_x * tiles_y;
  const int64_t S = 6 + F;
  for (int64_t t; (t = __atomic_fetch_add(next_tile, 1, __ATOMIC_RELAXED)) < n_tiles;) {
    const int64_t tx = t % tiles_x, ty = t / tiles_x;
    const int64_t x0 = tx * TILE, y0 = ty * TILE;
    const int rows = (int)std::min<int64_t>(TILE, H - y0);
    const int cols = (int)std::min<int64_t>(TILE, W - x0);
    const int64_t k0 = offsets[t], k1 = offsets[t + 1];
    if (k1 <= k0) continue;
    T* buf = new T[TPIX * (3 * F + 3)];
    T* Tr = buf;                      // transmittance behind the current Gaussian
    T* Tfin = buf + TPIX;             // final transmittance
    T* vT = buf + 2 * TPIX;           // dL/dT_final
    T* rec = buf + 3 * TPIX;          // blended features behind, normalised [TPIX * F]
    T* vacc = rec + TPIX * F;         // dL/daccum [TPIX * F]
    T* vacc_unused = vacc + TPIX * F; (void)vacc_unused;
    int32_t last[TPIX];
    int32_t max_last = 0;
    for (int p = 0; p < TPIX; ++p) {
      int i = p / TILE, j = p % TILE;
      last[p] = 0;
      Tr[p] = T(1); Tfin[p] = T(1); vT[p] = T(0);
      for (int64_t f = 0; f < F; ++f) { rec[p * F + f] = T(0); vacc[p * F + f] = T(0); }
      if (i < rows && j < cols) {
        const int64_t pix = (y0 + i) * W + (x0 + j);
        last[p] = out_last[pix];
        Tr[p] = out_T[pix]; Tfin[p] = out_T[pix]; vT[p] = v_T[pix];
        for (int64_t f = 0; f < F; ++f) vacc[p * F + f] = v_accum[pix * F + f];
        max_last = std::max(max_last, last[p]);
      }
    }
    for (int64_t k = k0 + max_last - 1; k >= k0; --k) {
      const int32_t local = (int32_t)(k - k0);
      const int64_t g = gauss[k];
      const T mx = means2d[2 * g], my = means2d[2 * g + 1];
      const T a = conics[3 * g], b = conics[3 * g + 1], c = conics[3 * g + 2];
      const T op = opac[g];
      Footprint<T> fp = make_footprint(mx, my, a, b, c, op);
      if (!fp.any) continue;
      const T* fg = feat + g * F;
      T g_mx = 0, g_my = 0, g_a = 0, g_b = 0, g_c = 0, g_op = 0;
      T* gf = v_pair + k * S + 6;
      int i0, i1;
      row_range(fp, T(y0), rows, i0, i1);
      for (int i = i0; i < i1; ++i) {
        const T py = T(y0 + i) + T(0.5);
        int j0, j1;
        row_span(fp, py, T(x0), j0, j1);
        j1 = std::min(j1, cols);
        for (int j = j0; j < j1; ++j) {
          const int p = i * TILE + j;
          if (local >= last[p]) continue;
          const T dx = mx - (T(x0 + j) + T(0.5));
          const T dy = my - py;
          const T power = T(-0.5) * (a * dx * dx + c * dy * dy) - b * dx * dy;
          if (power > T(0)) continue;
          const T G = std::exp(power);
          const T raw = op * G;
          const T alpha = std::min(Consts<T>::alpha_max, raw);
          if (alpha < Consts<T>::alpha_min) continue;
          const T one_m = T(1) - alpha;
          const T Tfront = Tr[p] / one_m;  // transmittance in front of this Gaussian
          const T w = alpha * Tfront;
          T v_alpha = 0;
          T* rp = rec + p * F;
          const T* vp = vacc + p * F;
          for (int64_t f = 0; f < F; ++f) {
            gf[f] += w * vp[f];
            v_alpha += (fg[f] - rp[f]) * vp[f];
            rp[f] = alpha * fg[f] + one_m * rp[f];
          }
          v_alpha = v_alpha * Tfront - vT[p] * Tfin[p] / one_m;
          Tr[p] = Tfront;
          if (raw <= Consts<T>::alpha_max) {
            g_op += G * v_alpha;
            const T v_power = op * G * v_alpha;
            // power = -0.5 (a dx^2 + c dy^2) - b dx dy, dx = mx - px
            g_mx += v_power * (-(a * dx + b * dy));
            g_my += v_power * (-(c * dy + b * dx));
            g_a += v_power * T(-0.5) * dx * dx;
            g_b += v_power * (-dx * dy);
            g_c += v_power * T(-0.5) * dy * dy;
          }
        }
      }
      T* gp = v_pair + k * S;
      gp[0] += g_mx; gp[1] += g_my; gp[2] += g_a; gp[3] += g_b; gp[4] += g_c; gp[5] += g_op;
    }
    delete[] buf;
  }
}

}  // namespace

extern "C" {

// Tile lists by counting sort: order [M] holds visible Gaussians front to back, rect [N, 4]
// (x_min, x_max, y_min, y_max) their tile rectangles; writes offsets [n_tiles + 1] and
// gauss [P] (P = sum of rectangle areas), each tile's list keeping the front-to-back order.
void splat_bin(int64_t m, const int64_t* order, const int64_t* rect, int64_t tiles_x,
               int64_t n_tiles, int64_t* offsets, int64_t* gauss) {
  for (int64_t t = 0; t <= n_tiles; ++t) offsets[t] = 0;
  for (int64_t k = 0; k < m; ++k) {
    const int64_t* r = rect + 4 * order[k];
    for (int64_t y = r[2]; y < r[3]; ++y)
      for (int64_t x = r[0]; x < r[1]; ++x) ++offsets[y * tiles_x + x + 1];
  }
  for (int64_t t = 0; t < n_tiles; ++t) offsets[t + 1] += offsets[t];
  int64_t* cursor = new int64_t[n_tiles];
  for (int64_t t = 0; t < n_tiles; ++t) cursor[t] = offsets[t];
  for (int64_t k = 0; k < m; ++k) {
    const int64_t g = order[k];
    const int64_t* r = rect + 4 * g;
    for (int64_t y = r[2]; y < r[3]; ++y)
      for (int64_t x = r[0]; x < r[1]; ++x) gauss[cursor[y * tiles_x + x]++] = g;
  }
  delete[] cursor;
}

int splat_abi_version() { return 4; }

void splat_forward_f32(int64_t tx, int64_t ty, int64_t W, int64_t H, int64_t F,
                       const int64_t* off, const int64_t* gs, const float* m, const float* co,
                       const float* op, const float* fe, float* acc, float* Tf, int32_t* last, int32_t* cnt,
                       int64_t* nth) {
  forward_impl<float>(tx, ty, W, H, F, off, gs, m, co, op, fe, acc, Tf, last, cnt, nth);
}
void splat_forward_f64(int64_t tx, int64_t ty, int64_t W, int64_t H, int64_t F,
                       const int64_t* off, const int64_t* gs, const double* m, const double* co,
                       const double* op, const double* fe, double* acc, double* Tf,
                       int32_t* last, int32_t* cnt, int64_t* nth) {
  forward_impl<double>(tx, ty, W, H, F, off, gs, m, co, op, fe, acc, Tf, last, cnt, nth);
}
void splat_backward_f32(int64_t tx, int64_t ty, int64_t W, int64_t H, int64_t F,
                        const int64_t* off, const int64_t* gs, const float* m, const float* co,
                        const float* op, const float* fe, const float* Tf, const int32_t* last,
                        const float* vacc, const float* vT, float* vpair, int64_t* nth) {
  backward_impl<float>(tx, ty, W, H, F, off, gs, m, co, op, fe, Tf, last, vacc, vT, vpair, nth);
}
void splat_backward_f64(int64_t tx, int64_t ty, int64_t W, int64_t H, int64_t F,
                        const int64_t* off, const int64_t* gs, const double* m,
                        const double* co, const double* op, const double* fe, const double* Tf,
                        const int32_t* last, const double* vacc, const double* vT,
                        double* vpair, int64_t* nth) {
  backward_impl<double>(tx, ty, W, H, F, off, gs, m, co, op, fe, Tf, last, vacc, vT, vpair, nth);
}

}  // extern "C"
