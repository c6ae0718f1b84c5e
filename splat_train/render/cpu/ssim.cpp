// SSIM of the 3DGS loss on the CPU: separable Gaussian filtering, forward and backward.
//
// Built and loaded like raster.cpp (plain C ABI, ctypes). Semantics of
// splat_train/losses.py ssim_map (the reference): per channel, local statistics with an
// 11 x 11 Gaussian window that is the outer product of a 1D window g (so filtering is a row pass
// then a column pass), zero padding, C1 = 0.01^2, C2 = 0.03^2. Returns the sum of the SSIM
// map per channel; the backward uses that the zero-padded 'same' filter with a symmetric window
// is its own adjoint:
//   m0 = F(a), m1 = F(b), m2 = F(a a), m3 = F(b b), m4 = F(a b)
//   S = (2 m0 m1 + C1)(2 (m4 - m0 m1) + C2) / ((m0^2 + m1^2 + C1)((m2 - m0^2) + (m3 - m1^2) + C2))
//   dL/da = F(G0) + 2 a F(G2) + b F(G4),  G_j = w dS/dm_j
// The images are read (and the gradient written) through element strides (sc, sy, sx) of
// channel, row and column: [C, H, W] planes (sc = H W, sy = W, sx = 1) or the rasterizer's
// [H, W, C] image (1, W C, C), which needs no transposed copy. The forward also sums |a - b|
// (the L1 term of the 3DGS loss) and the backward adds wl1 sign(a - b) to the gradient, so
// (1 - lambda) L1 + lambda (1 - SSIM) and its gradient take one pass each (the L1's five torch
// ops forward and backward were ~2 ms of an iteration on one thread). Work items are (channel,
// band of rows) from a shared counter, each writing its own rows and its own partial sums (the
// result does not depend on the thread count).

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr double C1 = 0.01 * 0.01;
constexpr double C2 = 0.03 * 0.03;

// The filters sum each output in a register over the taps and store it once, in blocks of B
// outputs: four 64-byte vectors of T (four independent FMA chains), then one vector, then
// scalars. The taps-outer loop over a whole row that this replaced loaded and stored every
// partial sum once per tap. Each output is still accumulated from 0 in tap order, as the
// scalar loop over the taps does.
template <typename T> constexpr int64_t kVec = 64 / sizeof(T);

// out[x] = sum_{k in [k0, k1)} g[k] src[(k - k0) stride + x] for x in [x, x + B) blocks up to W;
// returns the first x not done.
template <int64_t B, typename T>
inline int64_t filter_blocks(int64_t x, int64_t W, int k0, int k1, const T* g, const T* src, int64_t stride, T* out) {
  for (; x + B <= W; x += B) {
    T acc[B] = {};
    for (int k = k0; k < k1; ++k) {
      const T gk = g[k];
      const T* sk = src + (k - k0) * stride + x;
      for (int64_t l = 0; l < B; ++l) acc[l] += gk * sk[l];
    }
    for (int64_t l = 0; l < B; ++l) out[x + l] = acc[l];
  }
  return x;
}

template <typename T>
inline void filter(int64_t W, int k0, int k1, const T* g, const T* src, int64_t stride, T* out) {
  int64_t x = filter_blocks<4 * kVec<T>>(0, W, k0, k1, g, src, stride, out);
  x = filter_blocks<kVec<T>>(x, W, k0, k1, g, src, stride, out);
  filter_blocks<1>(x, W, k0, k1, g, src, stride, out);
}

// h[x] = sum_k g[k] p[x + k] for x in [0, W): the row pass of F on one row, p being the row with
// r = ws / 2 zeros on each side (W + ws - 1 entries).
template <typename T>
inline void row_filter(int64_t W, int ws, const T* g, const T* p, T* h) {
  filter(W, 0, ws, g, p, 1, h);
}

// o = column pass of F at image row y, from row-filtered rows tmp (row yy of the image at
// tmp + (yy - ylo) W, rows [ylo, yhi) available; rows outside [0, H) are the zero padding).
template <typename T>
inline void col_filter(int64_t H, int64_t W, int ws, const T* g, const T* tmp, int64_t ylo, int64_t y, T* o) {
  const int r = ws / 2;
  const int k0 = (int)std::max<int64_t>(0, r - y), k1 = (int)std::min<int64_t>(ws, H + r - y);
  filter(W, k0, k1, g, tmp + (y + k0 - r - ylo) * W, W, o);  // tap k reads image row y + k - r
}

// sum_x f(x) for x in [0, W) in double, in kLanes interleaved partial sums added in a fixed
// order (vectorised; one running double sum was a chain of dependent scalar adds per pixel,
// ~15 % of the forward). The order depends only on W, not on the thread count.
constexpr int kLanes = 8;
template <typename F>
inline double lane_sum(int64_t W, F&& f) {
  double acc[kLanes] = {};
  int64_t x = 0;
  for (; x + kLanes <= W; x += kLanes)
    for (int l = 0; l < kLanes; ++l) acc[l] += (double)f(x + l);
  double total = 0;
  for (; x < W; ++x) total += (double)f(x);
  for (int l = 0; l < kLanes; ++l) total += acc[l];
  return total;
}

// Work items are (channel, band of `band` rows): C * ceil(H / band) items from a shared counter,
// so both cores work on a 3-channel image (one channel per item left a core idle a third of the
// time). A band's row pass also covers the r rows above and below it that its column pass reads.
struct Layout {
  int64_t sc, sy, sx;  // element strides of channel, row, column
};

struct Bands {
  int64_t H, band, nb;
  Bands(int64_t H_, int64_t band_) : H(H_), band(band_ > 0 ? band_ : H_), nb((H_ + band - 1) / band) {}
};

// Per item: the 5 filtered planes m[c] of rows [y0, y1) (kept for the backward) and
// sums[c * nb + b] = sum of the SSIM map over those rows.
template <typename T>
void forward_impl(int64_t C, int64_t H, int64_t W, int ws, int64_t band, const T* g, const T* a, const T* b,
                  Layout L, T* m, double* sums, double* l1sums, int64_t* next) {
  const Bands bd(H, band);
  const int r = ws / 2;
  const int64_t P = H * W, PW = W + ws - 1, rows = std::min(H, bd.band + 2 * r);
  std::vector<T> pad(5 * PW, T(0)), tmp(5 * rows * W), srow(W);
  for (int64_t item; (item = __atomic_fetch_add(next, 1, __ATOMIC_RELAXED)) < C * bd.nb;) {
    const int64_t c = item / bd.nb, bi = item % bd.nb;
    const int64_t y0 = bi * bd.band, y1 = std::min(H, y0 + bd.band);
    const int64_t ylo = std::max<int64_t>(0, y0 - r), yhi = std::min(H, y1 + r), nr = yhi - ylo;
    const T* ac = a + c * L.sc;
    const T* bc = b + c * L.sc;
    T* mc = m + c * 5 * P;
    double l1 = 0;
    for (int64_t y = ylo; y < yhi; ++y) {
      const T* ar = ac + y * L.sy;
      const T* br = bc + y * L.sy;
      T* p0 = pad.data() + r;
      for (int64_t x = 0; x < W; ++x) {
        const T ax = ar[x * L.sx], bx = br[x * L.sx];
        p0[x] = ax;
        p0[PW + x] = bx;
        p0[2 * PW + x] = ax * ax;
        p0[3 * PW + x] = bx * bx;
        p0[4 * PW + x] = ax * bx;
      }
      if (y >= y0 && y < y1) l1 += lane_sum(W, [&](int64_t x) { return std::abs(p0[x] - p0[PW + x]); });
      for (int j = 0; j < 5; ++j) row_filter(W, ws, g, pad.data() + j * PW, tmp.data() + (j * nr + (y - ylo)) * W);
    }
    for (int j = 0; j < 5; ++j)
      for (int64_t y = y0; y < y1; ++y) col_filter(H, W, ws, g, tmp.data() + j * nr * W, ylo, y, mc + j * P + y * W);
    double total = 0;
    for (int64_t y = y0; y < y1; ++y) {
      const T* mrow = mc + y * W;
      for (int64_t x = 0; x < W; ++x) {  // the map's row (vectorised: no dependence between x)
        const T m0 = mrow[x], m1 = mrow[P + x];
        const T mu1_sq = m0 * m0, mu2_sq = m1 * m1, mu12 = m0 * m1;
        const T s11 = mrow[2 * P + x] - mu1_sq, s22 = mrow[3 * P + x] - mu2_sq, s12 = mrow[4 * P + x] - mu12;
        srow[x] = ((T(2) * mu12 + T(C1)) * (T(2) * s12 + T(C2))) / ((mu1_sq + mu2_sq + T(C1)) * (s11 + s22 + T(C2)));
      }
      total += lane_sum(W, [&](int64_t x) { return srow[x]; });
    }
    sums[item] = total;
    l1sums[item] = l1;
  }
}

// da = w * d(sum of the map)/da + wl1 sign(a - b) (sign(0) = 0, as torch's abs backward), from
// the filtered planes m of the forward, written with the images' strides; items as the forward.
template <typename T>
void backward_impl(int64_t C, int64_t H, int64_t W, int ws, int64_t band, const T* g, const T* a, const T* b,
                   Layout L, const T* m, T w, T wl1, T* da, int64_t* next) {
  const Bands bd(H, band);
  const int r = ws / 2;
  const int64_t P = H * W, PW = W + ws - 1, rows = std::min(H, bd.band + 2 * r);
  std::vector<T> pad(3 * PW, T(0)), tmp(3 * rows * W), F3(3 * W);
  for (int64_t item; (item = __atomic_fetch_add(next, 1, __ATOMIC_RELAXED)) < C * bd.nb;) {
    const int64_t c = item / bd.nb, bi = item % bd.nb;
    const int64_t y0 = bi * bd.band, y1 = std::min(H, y0 + bd.band);
    const int64_t ylo = std::max<int64_t>(0, y0 - r), yhi = std::min(H, y1 + r), nr = yhi - ylo;
    const T* ac = a + c * L.sc;
    const T* bc = b + c * L.sc;
    const T* mc = m + c * 5 * P;
    for (int64_t y = ylo; y < yhi; ++y) {
      T* G = pad.data() + r;
      for (int64_t x = 0; x < W; ++x) {
        const int64_t i = y * W + x;
        const T m0 = mc[i], m1 = mc[P + i];
        const T A1 = T(2) * m0 * m1 + T(C1);
        const T A2 = T(2) * (mc[4 * P + i] - m0 * m1) + T(C2);
        const T B1 = m0 * m0 + m1 * m1 + T(C1);
        const T B2 = (mc[2 * P + i] - m0 * m0) + (mc[3 * P + i] - m1 * m1) + T(C2);
        const T inv = T(1) / (B1 * B2);
        const T S = A1 * A2 * inv;
        const T dA1 = A2 * inv, dA2 = A1 * inv, dB1 = -S / B1, dB2 = -S / B2;
        G[x] = w * (dA1 * T(2) * m1 - dA2 * T(2) * m1 + dB1 * T(2) * m0 - dB2 * T(2) * m0);
        G[PW + x] = w * dB2;
        G[2 * PW + x] = w * dA2 * T(2);
      }
      for (int j = 0; j < 3; ++j) row_filter(W, ws, g, pad.data() + j * PW, tmp.data() + (j * nr + (y - ylo)) * W);
    }
    for (int64_t y = y0; y < y1; ++y) {
      for (int j = 0; j < 3; ++j) col_filter(H, W, ws, g, tmp.data() + j * nr * W, ylo, y, F3.data() + j * W);
      T* dr = da + c * L.sc + y * L.sy;
      const T* ar = ac + y * L.sy;
      const T* br = bc + y * L.sy;
      if (wl1 == T(0)) {
        for (int64_t x = 0; x < W; ++x)
          dr[x * L.sx] = F3[x] + T(2) * ar[x * L.sx] * F3[W + x] + br[x * L.sx] * F3[2 * W + x];
      } else {
        for (int64_t x = 0; x < W; ++x) {
          const T ax = ar[x * L.sx], bx = br[x * L.sx];
          const T sg = ax > bx ? wl1 : (ax < bx ? -wl1 : T(0));
          dr[x * L.sx] = F3[x] + T(2) * ax * F3[W + x] + bx * F3[2 * W + x] + sg;
        }
      }
    }
  }
}

}  // namespace

extern "C" {

int splat_ssim_abi_version() { return 3; }

// (sc, sy, sx): element strides of a, b and da (see the top of this file). sums, l1sums: one
// partial sum per work item (SSIM map, |a - b|).
#define SPLAT_SSIM_ENTRIES(T, sfx)                                                                                 \
  void splat_ssim_forward_##sfx(int64_t C, int64_t H, int64_t W, int64_t ws, int64_t band, const T* g, const T* a, \
                                const T* b, int64_t sc, int64_t sy, int64_t sx, T* m, double* sums,              \
                                double* l1sums, int64_t* next) {                                                 \
    forward_impl<T>(C, H, W, (int)ws, band, g, a, b, Layout{sc, sy, sx}, m, sums, l1sums, next);                 \
  }                                                                                                              \
  void splat_ssim_backward_##sfx(int64_t C, int64_t H, int64_t W, int64_t ws, int64_t band, const T* g,            \
                                 const T* a, const T* b, int64_t sc, int64_t sy, int64_t sx, const T* m,          \
                                 double w, double wl1, T* da, int64_t* next) {                                   \
    backward_impl<T>(C, H, W, (int)ws, band, g, a, b, Layout{sc, sy, sx}, m, (T)w, (T)wl1, da, next);            \
  }
SPLAT_SSIM_ENTRIES(float, f32)
SPLAT_SSIM_ENTRIES(double, f64)

}  // extern "C"
