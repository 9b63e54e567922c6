// Tile-based front-to-back alpha compositing of projected Gaussians: forward and backward.
//
// The rules are those of gscompress/render/torch_backend.py (the oracle these kernels are tested
// against): pixel (i, j) is evaluated at (i, j); alpha = min(0.99, o exp(power)); alpha < 1/255
// is skipped; compositing stops before the Gaussian that would bring T below 1e-4 (that one is
// left out).
//
// Layout of the work:
// - A parallel pass copies each (tile, Gaussian) entry's parameters, in tile list order, into a
//   packed array: the tile loops then read memory sequentially instead of jumping through
//   per-Gaussian arrays (those cache misses dominated an earlier version).
// - Tiles of 16x16 pixels are handed to threads with OpenMP dynamic scheduling. Within a tile
//   the loop runs Gaussian by Gaussian (front to back in the forward, back to front in the
//   backward); for each Gaussian only the tile rows, and the register-wide segments of a row
//   (8 pixels of float on AVX2 and AVX-512, starting at the Gaussian's first column), where
//   its alpha can reach 1/255 are visited. Each segment is one branch-free SIMD computation,
//   with the per-pixel state (T, accumulated features, ...) in tile-local arrays.
// - A segment's alpha is one long chain of dependent operations (the exponential's polynomial
//   above all), and a core overlaps only so much of one chain with the next. The alphas of a
//   Gaussian's segments (distinct pixels) are computed kInterleave at a time, statement by
//   statement; with FMA in the polynomial this made the forward and the backward faster on
//   AVX2 (docs/design-experiments.md, "Interleaved compositing and FMA").
// - The forward stores per pixel the final transmittance and the number of list entries it
//   consumed, so the backward is a single back-to-front pass that recovers T by division.
// - Per-Gaussian sums (contribution, gradients) are reduced over the pixels of a tile into the
//   entry's own slot, and the slots are added per Gaussian in list order at the end: no atomics,
//   no shared writes, and results that do not depend on the thread count or the schedule.

#include <torch/extension.h>

#include <omp.h>
#if defined(__FMA__)
#include <immintrin.h>
#endif

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <memory>
#include <type_traits>
#include <vector>

namespace {

constexpr int kTile = 16;
constexpr int kCh = 4;     // composited features: r, g, b, depth

template <typename scalar_t>
struct Rules {
  static constexpr scalar_t alpha_max = scalar_t(0.99);
  static constexpr scalar_t alpha_min = scalar_t(1.0 / 255.0);
  static constexpr scalar_t t_min = scalar_t(1e-4);
};

// The vector width in bytes: one register of the build target, at most 32. Vectors are never
// wider than a register: GCC splits wider generic vectors into pieces, but turns their
// comparisons and selects into scalar code (an earlier version with 16-float rows ran mostly
// scalar on AVX2). AVX-512 targets use 32 bytes too: with 16-float rows a segment spans a whole
// tile row, while most footprints are a few pixels wide, and on a Xeon with AVX-512 the
// forward + backward ran faster as an AVX2 build than with 64-byte vectors and faster again at
// 32 bytes with the native target (`bench/render.py --march`; docs/design-experiments.md,
// "Vector width on AVX-512").
#if defined(__AVX__)
constexpr int kVecBytes = 32;
#else
constexpr int kVecBytes = 16;
#endif

// One register of lanes (8 floats on AVX2); a Gaussian covers at most kSegs of them in a row.
template <typename S>
struct Simd;
template <>
struct Simd<float> {
  typedef float V __attribute__((vector_size(kVecBytes)));
  typedef int32_t I __attribute__((vector_size(kVecBytes)));
  typedef int32_t Int;
};
template <>
struct Simd<double> {
  typedef double V __attribute__((vector_size(kVecBytes)));
  typedef int64_t I __attribute__((vector_size(kVecBytes)));
  typedef int64_t Int;
};
template <typename S>
constexpr int kLanes = kVecBytes / int(sizeof(S));
template <typename S>
constexpr int kSegs = kTile / kLanes<S>;
static_assert(kTile % kLanes<double> == 0 && kTile % kLanes<float> == 0, "tile rows split evenly");

template <typename V, typename S>
inline V splat(S s) {
  return V{} + s;
}

// Sum of a vector's lanes, as a tree (a sequential loop over lanes is a long dependency chain).
template <typename V>
inline auto hsum(const V& v) {
  using S = std::remove_cv_t<std::remove_reference_t<decltype(v[0])>>;
  constexpr int n = int(sizeof(V) / sizeof(S));
  alignas(sizeof(V)) S lanes[n];
  std::memcpy(lanes, &v, sizeof(V));
  for (int half = n / 2; half >= 1; half /= 2) {
    for (int i = 0; i < half; ++i) lanes[i] += lanes[i + half];
  }
  return lanes[0];
}

// a * b + c, rounded once where the target has FMA. Used only inside vexp, whose polynomial is
// this file's own: everything the torch oracle computes too keeps the oracle's operations (the
// build turns off contraction, -ffp-contract=off), so both round alike.
using VF = Simd<float>::V;
using VD = Simd<double>::V;
#if defined(__FMA__)
inline VF fmadd(VF a, VF b, VF c) {
  return VF(_mm256_fmadd_ps(__m256(a), __m256(b), __m256(c)));
}
inline VD fmadd(VD a, VD b, VD c) {
  return VD(_mm256_fmadd_pd(__m256d(a), __m256d(b), __m256d(c)));
}
#else
template <typename V>
inline V fmadd(V a, V b, V c) {
  return a * b + c;
}
#endif

// exp(x) for x <= 0, accurate to about 1 ulp, in place on K whole vectors (libm's exp does not
// vectorise). The K vectors go through it statement by statement: the polynomial is a long chain
// of dependent operations, and K independent chains side by side let the core overlap them.
// x is clamped at -30: there alpha = o exp(x) is far below 1/255, so the clamp never changes a
// composited value, and it keeps every product in masked-out lanes away from denormals, which
// are very slow to compute with.
constexpr double kMinPower = -30.0;

#define EACH for (int k = 0; k < K; ++k)

template <int K>
inline void vexp(Simd<float>::V* x) {
  using V = Simd<float>::V;
  using I = Simd<float>::I;
  const float big = 12582912.0f;  // 1.5 * 2^23: adding it rounds to an integer
  V n[K], r[K], p[K];
  EACH x[k] = x[k] < float(kMinPower) ? splat<V>(float(kMinPower)) : x[k];
  EACH n[k] = (x[k] * 1.44269504088896341f + big) - big;
  EACH r[k] = x[k] - n[k] * 0.693359375f;
  EACH r[k] = r[k] - n[k] * -2.12194440e-4f;
  EACH p[k] = splat<V>(1.9875691500e-4f);
  static constexpr float coef[] = {1.3981999507e-3f, 8.3334519073e-3f, 4.1665795894e-2f,
                                   1.6666665459e-1f, 5.0000001201e-1f};
  for (float cf : coef) EACH p[k] = fmadd(p[k], r[k], splat<V>(cf));
  EACH {
    const V y = fmadd(p[k], r[k] * r[k], r[k]) + 1.0f;
    const I bits = (__builtin_convertvector(n[k], I) + 127) << 23;
    x[k] = y * V(bits);
  }
}

template <int K>
inline void vexp(Simd<double>::V* x) {
  using V = Simd<double>::V;
  using I = Simd<double>::I;
  const double big = 6755399441055744.0;  // 1.5 * 2^52
  V n[K], r[K], p[K];
  EACH x[k] = x[k] < kMinPower ? splat<V>(kMinPower) : x[k];
  EACH n[k] = (x[k] * 1.4426950408889634 + big) - big;
  EACH r[k] = x[k] - n[k] * 6.93145751953125e-1;
  EACH r[k] = r[k] - n[k] * 1.42860682030941723212e-6;
  // Taylor series to degree 13 on |r| <= ln(2)/2: truncation error below 1e-17.
  EACH p[k] = splat<V>(1.0 / 6227020800.0);
  static constexpr double coef[] = {1.0 / 479001600.0, 1.0 / 39916800.0, 1.0 / 3628800.0,
                                    1.0 / 362880.0,    1.0 / 40320.0,    1.0 / 5040.0,
                                    1.0 / 720.0,       1.0 / 120.0,      1.0 / 24.0,
                                    1.0 / 6.0,         0.5};
  for (double cf : coef) EACH p[k] = fmadd(p[k], r[k], splat<V>(cf));
  EACH {
    const V y = fmadd(p[k], r[k] * r[k], r[k]) + 1.0;
    const I bits = (__builtin_convertvector(n[k], I) + 1023) << 52;
    x[k] = y * V(bits);
  }
}

// Fields of one packed (tile, Gaussian) entry.
enum Field { kMx, kMy, kA, kB, kC, kO, kF0, kEx = kF0 + kCh, kEy, kFields };

// Packs the parameters of every list entry in list order (see the file comment): first one
// record per Gaussian (a sequential pass), then one copy of a record per entry, so that each
// entry costs a single random read. kEx / kEy are the half extents in pixels of the ellipse
// outside which the Gaussian's alpha is provably below 1/255: alpha = o exp(-q / 2) >= 1/255
// needs q <= 2 ln(255 o), and on that ellipse |dx| is at most sqrt(2 ln(255 o) Sigma_xx),
// Sigma = conic^-1. A 1e-3 relative + 1e-2 px margin keeps rounding from dropping a pixel that
// the exact test would keep (pixels inside are tested exactly). -1 marks a Gaussian that never
// reaches 1/255; +inf a degenerate conic (all pixels are tested).
template <typename scalar_t>
void pack_entries(const scalar_t* means2d, const scalar_t* conics, const scalar_t* opac,
                  const scalar_t* feats, int64_t n, const int64_t* ids, int64_t n_entries,
                  scalar_t* packed, int n_threads) {
  // Every record is written below: no zero-initialisation pass.
  std::unique_ptr<scalar_t[]> records(new scalar_t[size_t(n) * kFields]);
#pragma omp parallel num_threads(n_threads)
  {
#pragma omp for schedule(static)
    for (int64_t g = 0; g < n; ++g) {
      scalar_t* e = records.get() + g * kFields;
      const scalar_t a = conics[3 * g], b = conics[3 * g + 1], c = conics[3 * g + 2];
      const scalar_t o = opac[g];
      e[kMx] = means2d[2 * g];
      e[kMy] = means2d[2 * g + 1];
      e[kA] = a;
      e[kB] = b;
      e[kC] = c;
      e[kO] = o;
      for (int ch = 0; ch < kCh; ++ch) e[kF0 + ch] = feats[kCh * g + ch];
      const float q = 2.0f * std::log(255.0f * float(o)) * 1.001f + 1e-6f;
      const float det = float(a) * float(c) - float(b) * float(b);
      if (!(o >= Rules<scalar_t>::alpha_min)) {
        e[kEx] = e[kEy] = scalar_t(-1);
      } else if (!(q > 0.0f) || !(det > 0.0f) || !(a > 0) || !(c > 0) ||
                 !std::isfinite(q * float(c) / det) || !std::isfinite(q * float(a) / det)) {
        e[kEx] = e[kEy] = scalar_t(INFINITY);
      } else {
        e[kEx] = scalar_t(std::sqrt(q * float(c) / det) * 1.0001f + 1e-2f);
        e[kEy] = scalar_t(std::sqrt(q * float(a) / det) * 1.0001f + 1e-2f);
      }
    }
#pragma omp for schedule(static)
    for (int64_t s = 0; s < n_entries; ++s) {
      std::memcpy(packed + s * kFields, records.get() + ids[s] * kFields,
                  sizeof(scalar_t) * kFields);
    }
  }
}

// Range [lo, hi) of tile-local coordinates within `half` of `centre` (tile starts at `origin`).
inline void span(double centre, double half, int origin, int size, int& lo, int& hi) {
  const double l = std::ceil(centre - half) - origin;
  const double h = std::floor(centre + half) - origin + 1;
  lo = int(std::clamp(l, 0.0, double(size)));
  hi = int(std::clamp(h, 0.0, double(size)));
}

// Tile-local rows [y0, y1) and columns [x0, x1) where a packed entry's alpha can reach 1/255;
// false when there are none.
template <typename scalar_t>
inline bool entry_rect(const scalar_t* e, int tile_x, int tile_y, int tw, int th, int& x0,
                       int& x1, int& y0, int& y1) {
  if (e[kEx] < 0) return false;
  span(e[kMx], e[kEx], tile_x, tw, x0, x1);
  span(e[kMy], e[kEy], tile_y, th, y0, y1);
  return x0 < x1 && y0 < y1;
}

// Adds per-entry slots [n_entries, width] into per-Gaussian sums [n, width], in list order.
template <typename scalar_t>
void reduce_entries(const scalar_t* slots, const int64_t* ids, int64_t n_entries, int width,
                    scalar_t* out, int64_t n) {
  std::fill(out, out + n * width, scalar_t(0));
  for (int64_t s = 0; s < n_entries; ++s) {
    scalar_t* dst = out + ids[s] * width;
    for (int j = 0; j < width; ++j) dst[j] += slots[s * width + j];
  }
}

// Row stride of the per-pixel state: a tile row plus padding (L - 1 columns would do), so that
// a register-wide segment may start at any column of the row.
template <typename S>
constexpr int kStride = kTile + kLanes<S>;

template <typename V, typename S>
inline V load(const S* p) {
  V v;
  std::memcpy(&v, p, sizeof(V));
  return v;
}
template <typename V, typename S>
inline void store(S* p, const V& v) {
  std::memcpy(p, &v, sizeof(V));
}

// Row segments computed side by side (see vexp); 4 was the fastest of 1, 2, 3, 4, 6 and 8 on
// AVX2 (beyond 4, registers spill).
constexpr int kInterleave = 4;

// The columns [x0, x1) (tile-local) of one entry within a tile, as register-wide segments that
// start at x0 (a footprint at most a register wide takes one segment per row wherever it lies);
// per segment which lanes lie in [x0, x1), their x offset dx from the centre and a dx^2 (shared
// by every row the entry visits).
template <typename scalar_t>
struct EntryColumns {
  using V = typename Simd<scalar_t>::V;
  using I = typename Simd<scalar_t>::I;
  static constexpr int L = kLanes<scalar_t>;
  int x0, n_segs;
  I in_x[kSegs<scalar_t>];
  V dx[kSegs<scalar_t>], a_dx_dx[kSegs<scalar_t>];

  EntryColumns(const V& lane, int tile_x, int x0_, int x1, scalar_t mx, scalar_t a)
      : x0(x0_), n_segs((x1 - x0_ + L - 1) / L) {
    for (int sg = 0; sg < n_segs; ++sg) {
      const int first = x0 + sg * L;
      in_x[sg] = lane < scalar_t(x1 - first);
      dx[sg] = (lane + scalar_t(tile_x + first)) - mx;
      a_dx_dx[sg] = a * dx[sg] * dx[sg];
    }
  }
};

// K row segments of one entry (visits first .. first + K - 1 of its (y1 - y0) * n_segs, row by
// row): where their state lies, their offsets from the centre, the Gaussian G = exp(power), oG =
// o G and alpha = min(oG, alpha_max), computed alike for the forward and the backward.
template <typename scalar_t, int K>
struct Segments {
  using V = typename Simd<scalar_t>::V;
  int sg[K], p[K];
  scalar_t dy[K];
  V dx[K], G[K], oG[K], alpha[K];

  Segments(const EntryColumns<scalar_t>& col, int first, int y0, int tile_y, scalar_t my,
           scalar_t b, scalar_t c, scalar_t o) {
    int ly = y0 + first / col.n_segs, si = first % col.n_segs;
    EACH {
      sg[k] = si;
      p[k] = ly * kStride<scalar_t> + col.x0 + si * kLanes<scalar_t>;
      dy[k] = scalar_t(tile_y + ly) - my;
      dx[k] = col.dx[si];
      // Same operation order as the torch oracle, so both round alike.
      G[k] = scalar_t(-0.5) * (col.a_dx_dx[si] + c * dy[k] * dy[k]) - b * dx[k] * dy[k];
      if (++si == col.n_segs) si = 0, ++ly;
    }
    vexp<K>(G);
    EACH {
      oG[k] = o * G[k];
      alpha[k] = oG[k] > Rules<scalar_t>::alpha_max ? splat<V>(Rules<scalar_t>::alpha_max) : oG[k];
    }
  }
};

// Calls visit(std::integral_constant<int, K>, first) over n_visits row segments, kInterleave at
// a time and the remainder one by one.
template <typename Visit>
inline void interleaved(int n_visits, Visit&& visit) {
  int first = 0;
  for (; first + kInterleave <= n_visits; first += kInterleave) {
    visit(std::integral_constant<int, kInterleave>{}, first);
  }
  for (; first < n_visits; ++first) visit(std::integral_constant<int, 1>{}, first);
}

template <typename scalar_t>
void forward_impl(const scalar_t* packed, const int64_t* offsets, int width, int height,
                  int tiles_x, int tiles_y, scalar_t* out_feats, scalar_t* out_T,
                  int32_t* out_last, scalar_t* entry_weight, int n_threads) {
  using R = Rules<scalar_t>;
  using V = typename Simd<scalar_t>::V;
  using I = typename Simd<scalar_t>::I;
  using int_t = typename Simd<scalar_t>::Int;
  constexpr int L = kLanes<scalar_t>, RS = kStride<scalar_t>;
  const int n_tiles = tiles_x * tiles_y;

#pragma omp parallel num_threads(n_threads)
  {
    // Per-pixel state of a tile, row by row (pixel (lx, ly) at ly * RS + lx).
    alignas(64) scalar_t T[kTile * RS];
    alignas(64) scalar_t acc[kCh][kTile * RS];
    alignas(64) int_t alive[kTile * RS];  // -1 while the pixel is still compositing
    alignas(64) int_t last[kTile * RS];   // list entries consumed (last composited index + 1)
    V lane;
    for (int lx = 0; lx < L; ++lx) lane[lx] = scalar_t(lx);

#pragma omp for schedule(dynamic, 1)
    for (int t = 0; t < n_tiles; ++t) {
      const int tile_x = (t % tiles_x) * kTile, tile_y = (t / tiles_x) * kTile;
      const int tw = std::min(kTile, width - tile_x), th = std::min(kTile, height - tile_y);
      std::fill(T, T + kTile * RS, scalar_t(1));
      for (int ch = 0; ch < kCh; ++ch) std::fill(acc[ch], acc[ch] + kTile * RS, scalar_t(0));
      std::fill(last, last + kTile * RS, int_t(0));
      std::fill(alive, alive + kTile * RS, int_t(0));
      for (int ly = 0; ly < th; ++ly) std::fill(alive + ly * RS, alive + ly * RS + tw, int_t(-1));
      int n_active = tw * th;
      const int64_t begin = offsets[t], end = offsets[t + 1];
      if (entry_weight) std::fill(entry_weight + begin, entry_weight + end, scalar_t(0));

      for (int64_t s = begin; s < end && n_active > 0; ++s) {
        const scalar_t* e = packed + s * kFields;
        int x0, x1, y0, y1;
        if (!entry_rect(e, tile_x, tile_y, tw, th, x0, x1, y0, y1)) continue;
        const scalar_t mx = e[kMx], my = e[kMy], a = e[kA], b = e[kB], c = e[kC], o = e[kO];
        const EntryColumns<scalar_t> col(lane, tile_x, x0, x1, mx, a);
        const I k1 = splat<I>(int_t(s - begin + 1));
        V lane_w{};
        I lane_stop{};
        interleaved((y1 - y0) * col.n_segs, [&](auto k_const, int first) {
          constexpr int K = decltype(k_const)::value;
          const Segments<scalar_t, K> seg(col, first, y0, tile_y, my, b, c, o);
          EACH {
            const int p = seg.p[k];
            const V alpha = seg.alpha[k];
            const V Tp = load<V>(T + p);
            const V T_next = Tp * (scalar_t(1) - alpha);
            const I live = load<I>(alive + p);
            const I hit = col.in_x[seg.sg[k]] & live & (alpha >= R::alpha_min);
            const I stop = hit & (T_next < R::t_min);
            const I use = hit & ~stop;
            const V w = use ? alpha * Tp : V{};
            for (int ch = 0; ch < kCh; ++ch) {
              store(acc[ch] + p, load<V>(acc[ch] + p) + w * e[kF0 + ch]);
            }
            store(T + p, use ? T_next : Tp);
            store(last + p, use ? k1 : load<I>(last + p));
            store(alive + p, live & ~stop);
            lane_w += w;
            lane_stop -= stop;  // stop is -1 where a pixel stops
          }
        });
        n_active -= int(hsum(lane_stop));
        if (entry_weight) entry_weight[s] = hsum(lane_w);
      }

      for (int ly = 0; ly < th; ++ly) {
        for (int lx = 0; lx < tw; ++lx) {
          const int p = ly * RS + lx;
          const int64_t q = int64_t(tile_y + ly) * width + (tile_x + lx);
          for (int ch = 0; ch < kCh; ++ch) out_feats[kCh * q + ch] = acc[ch][p];
          out_T[q] = T[p];
          out_last[q] = int32_t(last[p]);
        }
      }
    }
  }
}

// Per-entry gradient slots: mean2d (2), conic (3), opacity (1), features (kCh).
constexpr int kGradSlots = 6 + kCh;

template <typename scalar_t>
void backward_impl(const scalar_t* packed, const int64_t* offsets, int width, int height,
                   int tiles_x, int tiles_y, const scalar_t* T_final, const int32_t* last_in,
                   const scalar_t* grad_feats, const scalar_t* grad_T, scalar_t* entry_grads,
                   int n_threads) {
  using R = Rules<scalar_t>;
  using V = typename Simd<scalar_t>::V;
  using I = typename Simd<scalar_t>::I;
  using int_t = typename Simd<scalar_t>::Int;
  constexpr int L = kLanes<scalar_t>, RS = kStride<scalar_t>;
  const int n_tiles = tiles_x * tiles_y;

#pragma omp parallel num_threads(n_threads)
  {
    // Per-pixel state of a tile, row by row (pixel (lx, ly) at ly * RS + lx).
    alignas(64) scalar_t T[kTile * RS];        // transmittance after the current Gaussian
    alignas(64) scalar_t gT_end[kTile * RS];   // dL/dT_final * T_final
    alignas(64) scalar_t gF[kCh][kTile * RS];  // dL/d(composited features)
    alignas(64) scalar_t S[kCh][kTile * RS];   // sum over the Gaussians behind of w_j f_j
    alignas(64) int_t last[kTile * RS];        // list entries the pixel consumed in the forward
    V lane;
    for (int lx = 0; lx < L; ++lx) lane[lx] = scalar_t(lx);

#pragma omp for schedule(dynamic, 1)
    for (int t = 0; t < n_tiles; ++t) {
      const int tile_x = (t % tiles_x) * kTile, tile_y = (t / tiles_x) * kTile;
      const int tw = std::min(kTile, width - tile_x), th = std::min(kTile, height - tile_y);
      int32_t k_max = 0;
      std::fill(T, T + kTile * RS, scalar_t(1));
      std::fill(gT_end, gT_end + kTile * RS, scalar_t(0));
      std::fill(last, last + kTile * RS, int_t(0));
      for (int ch = 0; ch < kCh; ++ch) {
        std::fill(gF[ch], gF[ch] + kTile * RS, scalar_t(0));
        std::fill(S[ch], S[ch] + kTile * RS, scalar_t(0));
      }
      for (int ly = 0; ly < th; ++ly) {
        for (int lx = 0; lx < tw; ++lx) {
          const int p = ly * RS + lx;
          const int64_t q = int64_t(tile_y + ly) * width + (tile_x + lx);
          T[p] = T_final[q];
          gT_end[p] = grad_T[q] * T_final[q];
          for (int ch = 0; ch < kCh; ++ch) gF[ch][p] = grad_feats[kCh * q + ch];
          last[p] = last_in[q];
          k_max = std::max(k_max, last_in[q]);
        }
      }
      const int64_t begin = offsets[t], end = offsets[t + 1];
      std::fill(entry_grads + begin * kGradSlots, entry_grads + end * kGradSlots, scalar_t(0));

      for (int64_t s = begin + k_max - 1; s >= begin; --s) {
        const scalar_t* e = packed + s * kFields;
        int x0, x1, y0, y1;
        if (!entry_rect(e, tile_x, tile_y, tw, th, x0, x1, y0, y1)) continue;
        const scalar_t mx = e[kMx], my = e[kMy], a = e[kA], b = e[kB], c = e[kC], o = e[kO];
        const EntryColumns<scalar_t> col(lane, tile_x, x0, x1, mx, a);
        const I index = splat<I>(int_t(s - begin));  // the entry's place in the tile list
        // Per-lane partial gradients, summed over the lanes once per entry.
        V d_mx{}, d_my{}, d_a{}, d_b{}, d_c{}, d_o{};
        V d_f[kCh] = {};
        interleaved((y1 - y0) * col.n_segs, [&](auto k_const, int first) {
          constexpr int K = decltype(k_const)::value;
          const Segments<scalar_t, K> seg(col, first, y0, tile_y, my, b, c, o);
          EACH {
            const int p = seg.p[k];
            const V G = seg.G[k], oG = seg.oG[k], alpha = seg.alpha[k], dx = seg.dx[k];
            const scalar_t dy = seg.dy[k];
            const I in_list = index < load<I>(last + p);
            const I hit = col.in_x[seg.sg[k]] & in_list & (alpha >= R::alpha_min);
            const V one_minus = scalar_t(1) - alpha;
            const V T_after = load<V>(T + p);
            const V T_before = T_after / one_minus;
            const V w = hit ? alpha * T_before : V{};
            // dL/dalpha: this Gaussian's own term, minus what it hides behind it, minus its
            // share of the final transmittance.
            V own{}, behind = load<V>(gT_end + p);
            for (int ch = 0; ch < kCh; ++ch) {
              const V g = load<V>(gF[ch] + p), s_behind = load<V>(S[ch] + p);
              own += g * e[kF0 + ch];
              behind += g * s_behind;
              d_f[ch] += w * g;
              store(S[ch] + p, s_behind + w * e[kF0 + ch]);
            }
            store(T + p, hit ? T_before : T_after);
            // The clamp at 0.99 passes no gradient once it bites.
            const I pass = hit & (oG <= R::alpha_max);
            const V d_alpha = pass ? T_before * own - behind / one_minus : V{};
            d_o += d_alpha * G;
            const V d_pow = d_alpha * alpha;
            d_a += scalar_t(-0.5) * d_pow * dx * dx;
            d_b -= d_pow * dx * dy;
            d_c += scalar_t(-0.5) * d_pow * dy * dy;
            d_mx += d_pow * (a * dx + b * dy);
            d_my += d_pow * (b * dx + c * dy);
          }
        });
        scalar_t* dst = entry_grads + s * kGradSlots;
        dst[0] = hsum(d_mx);
        dst[1] = hsum(d_my);
        dst[2] = hsum(d_a);
        dst[3] = hsum(d_b);
        dst[4] = hsum(d_c);
        dst[5] = hsum(d_o);
        for (int ch = 0; ch < kCh; ++ch) dst[6 + ch] = hsum(d_f[ch]);
      }
    }
  }
}

#undef EACH

void check_inputs(const torch::Tensor& means2d, const torch::Tensor& conics,
                  const torch::Tensor& opac, const torch::Tensor& feats,
                  const torch::Tensor& offsets, const torch::Tensor& ids, int64_t tiles_x,
                  int64_t tiles_y) {
  const auto n = means2d.size(0);
  TORCH_CHECK(means2d.dim() == 2 && means2d.size(1) == 2, "means2d must be [N, 2]");
  TORCH_CHECK(conics.dim() == 2 && conics.size(0) == n && conics.size(1) == 3,
              "conics must be [N, 3]");
  TORCH_CHECK(opac.dim() == 1 && opac.size(0) == n, "opacities must be [N]");
  TORCH_CHECK(feats.dim() == 2 && feats.size(0) == n && feats.size(1) == kCh,
              "features must be [N, 4]");
  TORCH_CHECK(offsets.dim() == 1 && offsets.size(0) == tiles_x * tiles_y + 1,
              "offsets must be [tiles + 1]");
  TORCH_CHECK(offsets.scalar_type() == torch::kInt64 && ids.scalar_type() == torch::kInt64,
              "offsets and ids must be int64");
  for (const auto* x : {&means2d, &conics, &opac, &feats}) {
    TORCH_CHECK(x->scalar_type() == means2d.scalar_type(), "all inputs must share a dtype");
    TORCH_CHECK(x->is_contiguous() && x->device().is_cpu(), "inputs must be contiguous CPU");
  }
  TORCH_CHECK(offsets.is_contiguous() && ids.is_contiguous(), "bins must be contiguous");
}

std::vector<torch::Tensor> composite_forward(torch::Tensor means2d, torch::Tensor conics,
                                             torch::Tensor opac, torch::Tensor feats,
                                             torch::Tensor offsets, torch::Tensor ids,
                                             int64_t width, int64_t height, int64_t tiles_x,
                                             int64_t tiles_y, bool want_contribution) {
  check_inputs(means2d, conics, opac, feats, offsets, ids, tiles_x, tiles_y);
  const auto n = means2d.size(0);
  const auto n_entries = ids.size(0);
  auto opts = means2d.options();
  auto packed = torch::empty({n_entries, kFields}, opts);
  auto out_feats = torch::empty({height, width, kCh}, opts);
  auto out_T = torch::empty({height, width}, opts);
  auto out_last = torch::empty({height, width}, opts.dtype(torch::kInt32));
  auto contrib = torch::empty({want_contribution ? n : 0}, opts);
  const int n_threads = std::max(1, at::get_num_threads());
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_forward", [&] {
    pack_entries<scalar_t>(means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                           opac.data_ptr<scalar_t>(), feats.data_ptr<scalar_t>(), n,
                           ids.data_ptr<int64_t>(), n_entries, packed.data_ptr<scalar_t>(),
                           n_threads);
    std::vector<scalar_t> entry_weight(want_contribution ? n_entries : 0);
    forward_impl<scalar_t>(packed.data_ptr<scalar_t>(), offsets.data_ptr<int64_t>(),
                           int(width), int(height), int(tiles_x), int(tiles_y),
                           out_feats.data_ptr<scalar_t>(), out_T.data_ptr<scalar_t>(),
                           out_last.data_ptr<int32_t>(),
                           want_contribution ? entry_weight.data() : nullptr, n_threads);
    if (want_contribution) {
      reduce_entries<scalar_t>(entry_weight.data(), ids.data_ptr<int64_t>(), n_entries, 1,
                               contrib.data_ptr<scalar_t>(), n);
    }
  });
  return {out_feats, out_T, out_last, contrib, packed};
}

std::vector<torch::Tensor> composite_backward(torch::Tensor packed, torch::Tensor offsets,
                                              torch::Tensor ids, int64_t n, int64_t width,
                                              int64_t height, int64_t tiles_x, int64_t tiles_y,
                                              torch::Tensor T_final, torch::Tensor last,
                                              torch::Tensor grad_feats, torch::Tensor grad_T) {
  const auto n_entries = ids.size(0);
  TORCH_CHECK(packed.dim() == 2 && packed.size(0) == n_entries && packed.size(1) == kFields,
              "packed entries must be [I, ", int(kFields), "]");
  TORCH_CHECK(offsets.dim() == 1 && offsets.size(0) == tiles_x * tiles_y + 1,
              "offsets must be [tiles + 1]");
  TORCH_CHECK(offsets.scalar_type() == torch::kInt64 && ids.scalar_type() == torch::kInt64,
              "offsets and ids must be int64");
  TORCH_CHECK(last.scalar_type() == torch::kInt32, "last must be int32");
  for (const auto* x : {&packed, &T_final, &grad_feats, &grad_T}) {
    TORCH_CHECK(x->scalar_type() == packed.scalar_type(), "all inputs must share a dtype");
  }
  for (const auto* x : {&packed, &offsets, &ids, &T_final, &last, &grad_feats, &grad_T}) {
    TORCH_CHECK(x->is_contiguous() && x->device().is_cpu(), "inputs must be contiguous CPU");
  }
  auto opts = packed.options();
  auto entry_grads = torch::empty({n_entries, kGradSlots}, opts);
  auto grads = torch::empty({n, kGradSlots}, opts);
  const int n_threads = std::max(1, at::get_num_threads());
  AT_DISPATCH_FLOATING_TYPES(packed.scalar_type(), "composite_backward", [&] {
    backward_impl<scalar_t>(packed.data_ptr<scalar_t>(), offsets.data_ptr<int64_t>(),
                            int(width), int(height), int(tiles_x), int(tiles_y),
                            T_final.data_ptr<scalar_t>(), last.data_ptr<int32_t>(),
                            grad_feats.data_ptr<scalar_t>(), grad_T.data_ptr<scalar_t>(),
                            entry_grads.data_ptr<scalar_t>(), n_threads);
    reduce_entries<scalar_t>(entry_grads.data_ptr<scalar_t>(), ids.data_ptr<int64_t>(),
                             n_entries, kGradSlots, grads.data_ptr<scalar_t>(), n);
  });
  // [N, 10] -> mean2d [N, 2], conic [N, 3], opacity [N], features [N, kCh]
  return {grads.slice(1, 0, 2), grads.slice(1, 2, 5), grads.select(1, 5),
          grads.slice(1, 6, 6 + kCh)};
}

}  // namespace

// project.cpp
std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor quats,
                                           torch::Tensor scales, torch::Tensor T, double fx,
                                           double fy, double cx, double cy, int64_t width,
                                           int64_t height, double near);
std::vector<torch::Tensor> project_backward(torch::Tensor means, torch::Tensor quats,
                                            torch::Tensor scales, torch::Tensor T, double fx,
                                            double fy, double cx, double cy, int64_t width,
                                            int64_t height, double near, torch::Tensor g_means2d,
                                            torch::Tensor g_conics, torch::Tensor g_depths,
                                            bool want_params);
std::vector<torch::Tensor> bin_tiles(torch::Tensor means2d, torch::Tensor radii,
                                     torch::Tensor depths, int64_t tiles_x, int64_t tiles_y);
// ssim.cpp
torch::Tensor blur_forward(torch::Tensor x, torch::Tensor k);
torch::Tensor blur_backward(torch::Tensor grad, torch::Tensor k, int64_t H, int64_t W);
std::vector<torch::Tensor> ssim_forward(torch::Tensor x, torch::Tensor y, torch::Tensor k,
                                        double c1, double c2);
torch::Tensor ssim_backward(torch::Tensor x, torch::Tensor y, torch::Tensor k,
                            torch::Tensor filtered, torch::Tensor grad, double c1, double c2);

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "gscompress cpu kernels: EWA projection, tile binning, compositing, SSIM";
  m.def("composite_forward", &composite_forward, "front-to-back compositing");
  m.def("composite_backward", &composite_backward, "back-to-front gradients");
  m.def("project_forward", &project_forward, "EWA projection of 3D Gaussians");
  m.def("project_backward", &project_backward,
        "gradients of the projection (want_params false: the camera's only)");
  m.def("bin_tiles", &bin_tiles, "tile lists, front to back");
  m.def("blur_forward", &blur_forward, "separable valid Gaussian filter (SSIM)");
  m.def("blur_backward", &blur_backward, "gradient of the separable filter");
  m.def("ssim_forward", &ssim_forward, "mean SSIM and its filtered maps");
  m.def("ssim_backward", &ssim_backward, "gradient of mean SSIM with respect to x");
}
