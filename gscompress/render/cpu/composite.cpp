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
//   (8 pixels of float on AVX2, 16 on AVX-512), where its alpha can reach 1/255 are visited.
//   Each segment is one branch-free SIMD computation, with the per-pixel state (T,
//   accumulated features, ...) in tile-local vectors.
// - The forward stores per pixel the final transmittance and the number of list entries it
//   consumed, so the backward is a single back-to-front pass that recovers T by division.
// - Per-Gaussian sums (contribution, gradients) are reduced over the pixels of a tile into the
//   entry's own slot, and the slots are added per Gaussian in list order at the end: no atomics,
//   no shared writes, and results that do not depend on the thread count or the schedule.

#include <torch/extension.h>

#include <omp.h>

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

// The build target's SIMD register width in bytes. Vectors are exactly one register wide: GCC
// splits wider generic vectors into pieces, but turns their comparisons and selects into scalar
// code (an earlier version with 16-float rows ran mostly scalar on AVX2).
#if defined(__AVX512F__)
constexpr int kVecBytes = 64;
#elif defined(__AVX__)
constexpr int kVecBytes = 32;
#else
constexpr int kVecBytes = 16;
#endif

// One register of lanes (8 floats on AVX2); a tile row of 16 pixels is kSegs of them.
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

// exp(x) for x <= 0, accurate to about 1 ulp, on a whole vector (libm's exp does not vectorise).
// x is clamped at -30: there alpha = o exp(x) is far below 1/255, so the clamp never changes a
// composited value, and it keeps every product in masked-out lanes away from denormals, which
// are very slow to compute with.
constexpr double kMinPower = -30.0;

inline Simd<float>::V vexp(Simd<float>::V x) {
  using V = Simd<float>::V;
  using I = Simd<float>::I;
  x = x < float(kMinPower) ? splat<V>(float(kMinPower)) : x;
  const float big = 12582912.0f;  // 1.5 * 2^23: adding it rounds to an integer
  const V n = (x * 1.44269504088896341f + big) - big;
  V r = x - n * 0.693359375f;
  r = r - n * -2.12194440e-4f;
  V p = splat<V>(1.9875691500e-4f);
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  const V y = p * (r * r) + r + 1.0f;
  const I bits = (__builtin_convertvector(n, I) + 127) << 23;
  return y * reinterpret_cast<const V&>(bits);
}

inline Simd<double>::V vexp(Simd<double>::V x) {
  using V = Simd<double>::V;
  using I = Simd<double>::I;
  x = x < kMinPower ? splat<V>(kMinPower) : x;
  const double big = 6755399441055744.0;  // 1.5 * 2^52
  const V n = (x * 1.4426950408889634 + big) - big;
  V r = x - n * 6.93145751953125e-1;
  r = r - n * 1.42860682030941723212e-6;
  // Taylor series to degree 13 on |r| <= ln(2)/2: truncation error below 1e-17.
  V p = splat<V>(1.0 / 6227020800.0);
  p = p * r + 1.0 / 479001600.0;
  p = p * r + 1.0 / 39916800.0;
  p = p * r + 1.0 / 3628800.0;
  p = p * r + 1.0 / 362880.0;
  p = p * r + 1.0 / 40320.0;
  p = p * r + 1.0 / 5040.0;
  p = p * r + 1.0 / 720.0;
  p = p * r + 1.0 / 120.0;
  p = p * r + 1.0 / 24.0;
  p = p * r + 1.0 / 6.0;
  p = p * r + 0.5;
  const V y = p * (r * r) + r + 1.0;
  const I bits = (__builtin_convertvector(n, I) + 1023) << 52;
  return y * reinterpret_cast<const V&>(bits);
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

// The columns of one entry within a tile: the row segments [v0, v1) that hold its columns
// [x0, x1) (tile-local), and per segment which lanes lie in them, their x offset from the
// centre and a dx^2 (shared by every row the entry visits).
template <typename scalar_t>
struct EntryColumns {
  using V = typename Simd<scalar_t>::V;
  using I = typename Simd<scalar_t>::I;
  static constexpr int L = kLanes<scalar_t>;
  int v0, v1;
  I in_x[kSegs<scalar_t>];
  V dx[kSegs<scalar_t>], a_dx_dx[kSegs<scalar_t>];

  EntryColumns(const V& lane, int tile_x, int x0, int x1, scalar_t mx, scalar_t a)
      : v0(x0 / L), v1((x1 + L - 1) / L) {
    for (int sg = v0; sg < v1; ++sg) {
      const V xs = lane + scalar_t(tile_x + sg * L);
      in_x[sg] = (xs > scalar_t(tile_x + x0) - scalar_t(0.5)) &
                 (xs < scalar_t(tile_x + x1) - scalar_t(0.5));
      dx[sg] = xs - mx;
      a_dx_dx[sg] = a * dx[sg] * dx[sg];
    }
  }
};

template <typename scalar_t>
void forward_impl(const scalar_t* packed, const int64_t* offsets, int width, int height,
                  int tiles_x, int tiles_y, scalar_t* out_feats, scalar_t* out_T,
                  int32_t* out_last, scalar_t* entry_weight, int n_threads) {
  using R = Rules<scalar_t>;
  using V = typename Simd<scalar_t>::V;
  using I = typename Simd<scalar_t>::I;
  using int_t = typename Simd<scalar_t>::Int;
  constexpr int L = kLanes<scalar_t>, NS = kSegs<scalar_t>;
  const int n_tiles = tiles_x * tiles_y;

#pragma omp parallel num_threads(n_threads)
  {
    // Per-pixel state, one vector per segment of a tile row (index ly * NS + segment).
    V T[kTile * NS];
    V acc[kCh][kTile * NS];
    I alive[kTile * NS];  // all ones while the pixel is still compositing
    I last[kTile * NS];   // list entries consumed (index of the last composited one + 1)
    V lane;
    for (int lx = 0; lx < L; ++lx) lane[lx] = scalar_t(lx);

#pragma omp for schedule(dynamic, 1)
    for (int t = 0; t < n_tiles; ++t) {
      const int tile_x = (t % tiles_x) * kTile, tile_y = (t / tiles_x) * kTile;
      const int tw = std::min(kTile, width - tile_x), th = std::min(kTile, height - tile_y);
      for (int ly = 0; ly < kTile; ++ly) {
        for (int sg = 0; sg < NS; ++sg) {
          const int v = ly * NS + sg;
          T[v] = splat<V>(scalar_t(1));
          for (int ch = 0; ch < kCh; ++ch) acc[ch][v] = V{};
          alive[v] = (lane < scalar_t(tw - sg * L)) & splat<I>(int_t(ly < th ? -1 : 0));
          last[v] = I{};
        }
      }
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
        for (int ly = y0; ly < y1; ++ly) {
          const scalar_t dy = scalar_t(tile_y + ly) - my;
          for (int sg = col.v0; sg < col.v1; ++sg) {
            const int v = ly * NS + sg;
            // Same operation order as the torch oracle, so both round alike.
            const V dx = col.dx[sg];
            const V power = scalar_t(-0.5) * (col.a_dx_dx[sg] + c * dy * dy) - b * dx * dy;
            const V oG = o * vexp(power);
            const V alpha = oG > R::alpha_max ? splat<V>(R::alpha_max) : oG;
            const V Tp = T[v];
            const V T_next = Tp * (scalar_t(1) - alpha);
            const I hit = col.in_x[sg] & alive[v] & (alpha >= R::alpha_min);
            const I stop = hit & (T_next < R::t_min);
            const I use = hit & ~stop;
            const V w = use ? alpha * Tp : V{};
            for (int ch = 0; ch < kCh; ++ch) acc[ch][v] += w * e[kF0 + ch];
            T[v] = use ? T_next : Tp;
            last[v] = use ? k1 : last[v];
            alive[v] &= ~stop;
            lane_w += w;
            lane_stop -= stop;  // stop is -1 where a pixel stops
          }
        }
        n_active -= int(hsum(lane_stop));
        if (entry_weight) entry_weight[s] = hsum(lane_w);
      }

      for (int ly = 0; ly < th; ++ly) {
        for (int lx = 0; lx < tw; ++lx) {
          const int v = ly * NS + lx / L, l = lx % L;
          const int64_t q = int64_t(tile_y + ly) * width + (tile_x + lx);
          for (int ch = 0; ch < kCh; ++ch) out_feats[kCh * q + ch] = acc[ch][v][l];
          out_T[q] = T[v][l];
          out_last[q] = int32_t(last[v][l]);
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
  constexpr int L = kLanes<scalar_t>, NS = kSegs<scalar_t>;
  const int n_tiles = tiles_x * tiles_y;

#pragma omp parallel num_threads(n_threads)
  {
    // Per-pixel state, one vector per segment of a tile row (index ly * NS + segment).
    V T[kTile * NS];        // transmittance after the current Gaussian
    V gT_end[kTile * NS];   // dL/dT_final * T_final
    V gF[kCh][kTile * NS];  // dL/d(composited features)
    V S[kCh][kTile * NS];   // sum over the Gaussians behind of w_j f_j
    I last[kTile * NS];     // list entries consumed by the pixel in the forward
    V lane;
    for (int lx = 0; lx < L; ++lx) lane[lx] = scalar_t(lx);

#pragma omp for schedule(dynamic, 1)
    for (int t = 0; t < n_tiles; ++t) {
      const int tile_x = (t % tiles_x) * kTile, tile_y = (t / tiles_x) * kTile;
      const int tw = std::min(kTile, width - tile_x), th = std::min(kTile, height - tile_y);
      int32_t k_max = 0;
      for (int v = 0; v < kTile * NS; ++v) {
        T[v] = splat<V>(scalar_t(1));
        gT_end[v] = V{};
        last[v] = I{};
        for (int ch = 0; ch < kCh; ++ch) gF[ch][v] = S[ch][v] = V{};
      }
      for (int ly = 0; ly < th; ++ly) {
        for (int lx = 0; lx < tw; ++lx) {
          const int v = ly * NS + lx / L, l = lx % L;
          const int64_t q = int64_t(tile_y + ly) * width + (tile_x + lx);
          T[v][l] = T_final[q];
          gT_end[v][l] = grad_T[q] * T_final[q];
          for (int ch = 0; ch < kCh; ++ch) gF[ch][v][l] = grad_feats[kCh * q + ch];
          last[v][l] = last_in[q];
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
        const I k = splat<I>(int_t(s - begin));
        // Per-lane partial gradients, summed over the lanes once per entry.
        V d_mx{}, d_my{}, d_a{}, d_b{}, d_c{}, d_o{};
        V d_f[kCh] = {};
        for (int ly = y0; ly < y1; ++ly) {
          const scalar_t dy = scalar_t(tile_y + ly) - my;
          for (int sg = col.v0; sg < col.v1; ++sg) {
            const int v = ly * NS + sg;
            const V dx = col.dx[sg];
            const V power = scalar_t(-0.5) * (col.a_dx_dx[sg] + c * dy * dy) - b * dx * dy;
            const V G = vexp(power);
            const V oG = o * G;
            const V alpha = oG > R::alpha_max ? splat<V>(R::alpha_max) : oG;
            const I hit = col.in_x[sg] & (k < last[v]) & (alpha >= R::alpha_min);
            const V one_minus = scalar_t(1) - alpha;
            const V T_before = T[v] / one_minus;
            const V w = hit ? alpha * T_before : V{};
            // dL/dalpha: this Gaussian's own term, minus what it hides behind it, minus its
            // share of the final transmittance.
            V own{}, behind = gT_end[v];
            for (int ch = 0; ch < kCh; ++ch) {
              own += gF[ch][v] * e[kF0 + ch];
              behind += gF[ch][v] * S[ch][v];
              d_f[ch] += w * gF[ch][v];
              S[ch][v] += w * e[kF0 + ch];
            }
            T[v] = hit ? T_before : T[v];
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
        }
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
