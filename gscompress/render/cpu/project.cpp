// EWA projection of 3D Gaussians (forward and backward, one pass per Gaussian) and the binning
// of the projected Gaussians into 16x16 tiles.
//
// The same arithmetic as `project_gaussians` in gscompress/render/projection.py (the oracle
// these kernels are tested against, through the cpu and torch render backends), in the same
// order, so that both round alike; that file's docstring holds the conventions. Written out by
// hand because the torch version is some 60 tensor operations forward and as many backward on
// [N]-sized tensors, whose per-operation overhead made it a third of a tracking iteration.
//
// `bin_tiles` gives the lists of `projection.bin_tiles` exactly: by tile, then by depth rounded to
// float32, ties by Gaussian index (a counting pass fills each tile in index order, then a stable
// sort by depth per tile).
//
// The backward recomputes each Gaussian's forward quantities instead of saving them. The
// gradient of the camera transform is a sum over all Gaussians, taken in double over fixed
// chunks of them and then over the chunks in order, so it does not depend on the thread count.

#include <torch/extension.h>

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

namespace {

constexpr double kEps2d = 0.3;  // projection.EPS2D
constexpr int kTile = 16;       // projection.TILE_SIZE

struct Camera {
  double fx, fy, cx, cy, near;
  int width, height;
  // Clamp limits of x/z and y/z for the Jacobian (0.3 tan(fov / 2) beyond the outer pixel edges).
  double u_lo, u_hi, v_lo, v_hi;

  Camera(double fx_, double fy_, double cx_, double cy_, int w, int h, double near_)
      : fx(fx_), fy(fy_), cx(cx_), cy(cy_), near(near_), width(w), height(h) {
    const double tan_x = 0.5 * w / fx, tan_y = 0.5 * h / fy;
    u_lo = (cx + 0.5) / fx + 0.3 * tan_x;
    u_hi = (w - 0.5 - cx) / fx + 0.3 * tan_x;
    v_lo = (cy + 0.5) / fy + 0.3 * tan_y;
    v_hi = (h - 0.5 - cy) / fy + 0.3 * tan_y;
  }
};

// The rotation W and translation t of a [4, 4] row-major world-to-camera transform.
template <typename S>
struct Pose {
  S W[3][3], t[3];
  explicit Pose(const S* T) {
    for (int i = 0; i < 3; ++i) {
      for (int k = 0; k < 3; ++k) W[i][k] = T[4 * i + k];
      t[i] = T[4 * i + 3];
    }
  }
};

// Every forward quantity of one Gaussian that the backward needs.
template <typename S>
struct Proj {
  S p[3];        // camera-frame centre x, y, z
  S zs;          // z, or 1 when culled (z < near)
  bool in_front;
  S qn[4];       // normalised quaternion w, x, y, z
  S qnorm;
  S R[3][3];     // rotation
  S M[3][3];     // rows of R S
  S WM[3][3];    // rows of W R S
  S u, v;        // clamped x/z, y/z
  bool u_free, v_free;  // the clamp did not bite (gradient passes)
  S iz, Fu, Fv;  // 1/zs, fx/zs, fy/zs
  S ru[3], rv[3];
  S sxx, sxy, syy, det, ds;
  bool ok;
};

template <typename S>
inline void project_one(const S* m, const S* q, const S* s, const S W[3][3], const S t[3],
                        const Camera& cam, Proj<S>& o) {
  for (int i = 0; i < 3; ++i) {
    // (means * W[i]).sum(-1) + t[i]
    o.p[i] = (m[0] * W[i][0] + m[1] * W[i][1]) + m[2] * W[i][2] + t[i];
  }
  const S z = o.p[2];
  o.in_front = z >= S(cam.near);
  o.zs = o.in_front ? z : S(1);
  // quats / quats.norm()
  o.qnorm = std::sqrt(((q[0] * q[0] + q[1] * q[1]) + q[2] * q[2]) + q[3] * q[3]);
  for (int k = 0; k < 4; ++k) o.qn[k] = q[k] / o.qnorm;
  const S w = o.qn[0], x = o.qn[1], y = o.qn[2], zq = o.qn[3];
  o.R[0][0] = 1 - 2 * (y * y + zq * zq);
  o.R[0][1] = 2 * (x * y - w * zq);
  o.R[0][2] = 2 * (x * zq + w * y);
  o.R[1][0] = 2 * (x * y + w * zq);
  o.R[1][1] = 1 - 2 * (x * x + zq * zq);
  o.R[1][2] = 2 * (y * zq - w * x);
  o.R[2][0] = 2 * (x * zq - w * y);
  o.R[2][1] = 2 * (y * zq + w * x);
  o.R[2][2] = 1 - 2 * (x * x + y * y);
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) o.M[r][c] = o.R[r][c] * s[c];
  }
  for (int i = 0; i < 3; ++i) {
    for (int c = 0; c < 3; ++c) {
      o.WM[i][c] = (W[i][0] * o.M[0][c] + W[i][1] * o.M[1][c]) + W[i][2] * o.M[2][c];
    }
  }
  const S ux = o.p[0] / o.zs, vy = o.p[1] / o.zs;
  const S ulo = -S(cam.u_lo), uhi = S(cam.u_hi), vlo = -S(cam.v_lo), vhi = S(cam.v_hi);
  o.u = std::min(std::max(ux, ulo), uhi);
  o.v = std::min(std::max(vy, vlo), vhi);
  o.u_free = ux >= ulo && ux <= uhi;
  o.v_free = vy >= vlo && vy <= vhi;
  o.iz = S(1) / o.zs;
  o.Fu = S(cam.fx) * o.iz;
  o.Fv = S(cam.fy) * o.iz;
  for (int c = 0; c < 3; ++c) {
    o.ru[c] = o.Fu * (o.WM[0][c] - o.u * o.WM[2][c]);
    o.rv[c] = o.Fv * (o.WM[1][c] - o.v * o.WM[2][c]);
  }
  o.sxx = ((o.ru[0] * o.ru[0] + o.ru[1] * o.ru[1]) + o.ru[2] * o.ru[2]) + S(kEps2d);
  o.sxy = (o.ru[0] * o.rv[0] + o.ru[1] * o.rv[1]) + o.ru[2] * o.rv[2];
  o.syy = ((o.rv[0] * o.rv[0] + o.rv[1] * o.rv[1]) + o.rv[2] * o.rv[2]) + S(kEps2d);
  o.det = o.sxx * o.syy - o.sxy * o.sxy;
  o.ok = o.in_front && o.det > 0;
  o.ds = o.ok ? o.det : S(1);
}

// Half-open tile range [lo, hi) of a footprint centred at c with radius r, clamped to [0, n].
template <typename S>
inline void tile_range(S c, S r, int n, int64_t& lo, int64_t& hi) {
  const S l = std::ceil((c - r - S(kTile - 1)) / S(kTile));
  const S h = std::floor((c + r) / S(kTile)) + 1;
  lo = int64_t(std::min(std::max(l, S(0)), S(n)));
  hi = int64_t(std::min(std::max(h, S(0)), S(n)));
}

template <typename S>
void forward_impl(const S* means, const S* quats, const S* scales, const S* T, const Camera& cam,
                  int64_t n, S* means2d, S* conics, S* depths, int32_t* radii, int n_threads) {
  const Pose<S> pose(T);
  const auto& W = pose.W;
  const auto& t = pose.t;
  const int tiles_x = (cam.width + kTile - 1) / kTile, tiles_y = (cam.height + kTile - 1) / kTile;
#pragma omp parallel for schedule(static) num_threads(n_threads)
  for (int64_t g = 0; g < n; ++g) {
    Proj<S> o;
    project_one(means + 3 * g, quats + 4 * g, scales + 3 * g, W, t, cam, o);
    conics[3 * g] = o.syy / o.ds;
    conics[3 * g + 1] = -o.sxy / o.ds;
    conics[3 * g + 2] = o.sxx / o.ds;
    const S mu = S(cam.fx) * o.p[0] / o.zs + S(cam.cx);
    const S mv = S(cam.fy) * o.p[1] / o.zs + S(cam.cy);
    means2d[2 * g] = mu;
    means2d[2 * g + 1] = mv;
    depths[g] = o.p[2];
    // radius: ceil(3 sqrt(lambda_max)) of the dilated covariance, 0 when culled or off-image
    const S mid = S(0.5) * (o.sxx + o.syy);
    const S lam = mid + std::sqrt(std::max(mid * mid - o.det, S(0)));
    S r = std::ceil(S(3) * std::sqrt(std::max(lam, S(0))));
    if (!(o.ok && std::isfinite(r))) r = 0;
    r = std::min(r, S(1 << 30));
    const int32_t ri = int32_t(r);
    int64_t x0 = 0, x1 = 0, y0 = 0, y1 = 0;
    if (ri > 0) {  // (a culled centre may be NaN, which must not reach an integer conversion)
      tile_range(mu, S(ri), tiles_x, x0, x1);
      tile_range(mv, S(ri), tiles_y, y0, y1);
    }
    radii[g] = (x1 > x0 && y1 > y0) ? ri : 0;
  }
}

// The camera transform's gradient, W (9, row-major) then t (3), is summed in double over fixed
// chunks of Gaussians (in parallel), and the chunks' sums are added in order by the caller.
// With d_means == nullptr the per-Gaussian gradients (means, quats, scales) are skipped: the
// camera's gradient does not depend on them, so it comes out the same bit for bit.
constexpr int kPoseSlots = 12;
constexpr int64_t kChunk = 1024;

template <typename S>
void backward_impl(const S* means, const S* quats, const S* scales, const S* T, const Camera& cam,
                   int64_t n, const S* g_means2d, const S* g_conics, const S* g_depths,
                   S* d_means, S* d_quats, S* d_scales, double* chunk_sums, int n_threads) {
  const Pose<S> pose(T);
  const auto& W = pose.W;
  const auto& t = pose.t;
  const int64_t n_chunks = (n + kChunk - 1) / kChunk;
#pragma omp parallel for schedule(static) num_threads(n_threads)
  for (int64_t chunk = 0; chunk < n_chunks; ++chunk) {
    double* sum = chunk_sums + kPoseSlots * chunk;
    std::fill(sum, sum + kPoseSlots, 0.0);
    for (int64_t g = chunk * kChunk; g < std::min(n, (chunk + 1) * kChunk); ++g) {
      const S* m = means + 3 * g;
      Proj<S> o;
      project_one(m, quats + 4 * g, scales + 3 * g, W, t, cam, o);
      const S fx = S(cam.fx), fy = S(cam.fy);
      // conics = (syy, -sxy, sxx) / ds, ds = det where ok (else the constant 1)
      const S ga = g_conics[3 * g], gb = g_conics[3 * g + 1], gc = g_conics[3 * g + 2];
      const S inv = S(1) / o.ds;
      S d_sxx = gc * inv, d_syy = ga * inv, d_sxy = -gb * inv;
      if (o.ok) {
        const S d_det = -(ga * o.syy - gb * o.sxy + gc * o.sxx) * inv * inv;
        d_sxx += d_det * o.syy;
        d_syy += d_det * o.sxx;
        d_sxy -= S(2) * d_det * o.sxy;
      }
      // s_xx = |ru|^2 + eps, s_xy = ru . rv, s_yy = |rv|^2 + eps
      S d_ru[3], d_rv[3];
      for (int c = 0; c < 3; ++c) {
        d_ru[c] = S(2) * o.ru[c] * d_sxx + o.rv[c] * d_sxy;
        d_rv[c] = S(2) * o.rv[c] * d_syy + o.ru[c] * d_sxy;
      }
      // ru = Fu (WM0 - u WM2), rv = Fv (WM1 - v WM2)
      S d_WM[3][3] = {};
      S d_Fu = 0, d_Fv = 0, d_u = 0, d_v = 0;
      for (int c = 0; c < 3; ++c) {
        d_Fu += d_ru[c] * (o.WM[0][c] - o.u * o.WM[2][c]);
        d_Fv += d_rv[c] * (o.WM[1][c] - o.v * o.WM[2][c]);
        d_WM[0][c] += d_ru[c] * o.Fu;
        d_WM[1][c] += d_rv[c] * o.Fv;
        d_WM[2][c] -= d_ru[c] * o.Fu * o.u + d_rv[c] * o.Fv * o.v;
        d_u -= d_ru[c] * o.Fu * o.WM[2][c];
        d_v -= d_rv[c] * o.Fv * o.WM[2][c];
      }
      // Fu = fx / zs, Fv = fy / zs; u = clamp(x / zs), v = clamp(y / zs); means2d = f p / zs + c
      const S d_iz = fx * d_Fu + fy * d_Fv;
      const S gu = g_means2d[2 * g], gv = g_means2d[2 * g + 1];
      const S izs2 = S(1) / (o.zs * o.zs);
      S d_p[3] = {0, 0, 0};
      S d_zs = -d_iz * izs2;
      if (o.u_free) {
        d_p[0] += d_u / o.zs;
        d_zs -= d_u * o.p[0] * izs2;
      }
      if (o.v_free) {
        d_p[1] += d_v / o.zs;
        d_zs -= d_v * o.p[1] * izs2;
      }
      d_p[0] += gu * fx / o.zs;
      d_p[1] += gv * fy / o.zs;
      d_zs -= (gu * fx * o.p[0] + gv * fy * o.p[1]) * izs2;
      d_p[2] = g_depths[g] + (o.in_front ? d_zs : S(0));
      // WM[i] = sum_k W[i][k] M[k]; M[k][c] = R[k][c] s[c]
      S d_M[3][3];
      for (int k = 0; k < 3; ++k) {
        for (int c = 0; c < 3; ++c) {
          d_M[k][c] = d_WM[0][c] * W[0][k] + d_WM[1][c] * W[1][k] + d_WM[2][c] * W[2][k];
        }
      }
      for (int i = 0; i < 3; ++i) {
        for (int k = 0; k < 3; ++k) {
          S acc = d_p[i] * m[k];  // p = W m + t
          for (int c = 0; c < 3; ++c) acc += d_WM[i][c] * o.M[k][c];
          sum[3 * i + k] += double(acc);
        }
        sum[9 + i] += double(d_p[i]);
      }
      if (d_means == nullptr) continue;  // only the camera's gradient is wanted (tracking)
      for (int k = 0; k < 3; ++k) {
        d_means[3 * g + k] = d_p[0] * W[0][k] + d_p[1] * W[1][k] + d_p[2] * W[2][k];
      }
      S d_R[3][3];
      for (int c = 0; c < 3; ++c) {
        S ds_c = 0;
        for (int k = 0; k < 3; ++k) {
          d_R[k][c] = d_M[k][c] * scales[3 * g + c];
          ds_c += d_M[k][c] * o.R[k][c];
        }
        d_scales[3 * g + c] = ds_c;
      }
      // R of the normalised quaternion (w, x, y, z), then through the normalisation
      const S w = o.qn[0], x = o.qn[1], y = o.qn[2], z = o.qn[3];
      const S dw = 2 * (-z * d_R[0][1] + y * d_R[0][2] + z * d_R[1][0] - x * d_R[1][2] -
                        y * d_R[2][0] + x * d_R[2][1]);
      const S dx = 2 * (y * d_R[0][1] + z * d_R[0][2] + y * d_R[1][0] - 2 * x * d_R[1][1] -
                        w * d_R[1][2] + z * d_R[2][0] + w * d_R[2][1] - 2 * x * d_R[2][2]);
      const S dy = 2 * (-2 * y * d_R[0][0] + x * d_R[0][1] + w * d_R[0][2] + x * d_R[1][0] +
                        z * d_R[1][2] - w * d_R[2][0] + z * d_R[2][1] - 2 * y * d_R[2][2]);
      const S dz = 2 * (-2 * z * d_R[0][0] - w * d_R[0][1] + x * d_R[0][2] + w * d_R[1][0] -
                        2 * z * d_R[1][1] + y * d_R[1][2] + x * d_R[2][0] + y * d_R[2][1]);
      const S dqn[4] = {dw, dx, dy, dz};
      const S dot = w * dw + x * dx + y * dy + z * dz;
      for (int k = 0; k < 4; ++k) d_quats[4 * g + k] = (dqn[k] - o.qn[k] * dot) / o.qnorm;
    }
  }
}

template <typename S>
void bin_impl(const S* means2d, const int32_t* radii, const S* depths, int64_t n, int tiles_x,
              int tiles_y, int64_t* offsets, std::vector<int64_t>& ids, int n_threads) {
  const int64_t n_tiles = int64_t(tiles_x) * tiles_y;
  std::vector<int64_t> rect(size_t(n) * 4);
  std::vector<int64_t> count(n_tiles + 1, 0);
  for (int64_t g = 0; g < n; ++g) {
    int64_t* r = rect.data() + 4 * g;
    if (radii[g] <= 0) {
      r[0] = r[1] = r[2] = r[3] = 0;
      continue;
    }
    tile_range(means2d[2 * g], S(radii[g]), tiles_x, r[0], r[1]);
    tile_range(means2d[2 * g + 1], S(radii[g]), tiles_y, r[2], r[3]);
    for (int64_t ty = r[2]; ty < r[3]; ++ty) {
      for (int64_t tx = r[0]; tx < r[1]; ++tx) ++count[ty * tiles_x + tx + 1];
    }
  }
  offsets[0] = 0;
  for (int64_t t = 0; t < n_tiles; ++t) offsets[t + 1] = offsets[t] + count[t + 1];
  ids.resize(size_t(offsets[n_tiles]));
  std::vector<int64_t> cursor(offsets, offsets + n_tiles);
  for (int64_t g = 0; g < n; ++g) {  // each tile's list in increasing Gaussian index
    const int64_t* r = rect.data() + 4 * g;
    for (int64_t ty = r[2]; ty < r[3]; ++ty) {
      for (int64_t tx = r[0]; tx < r[1]; ++tx) ids[cursor[ty * tiles_x + tx]++] = g;
    }
  }
  // The sort key of `projection.bin_tiles`: the bits of the float32 depth, which order like
  // its value for the positive depths of visible Gaussians.
  std::vector<int32_t> key(n);
  for (int64_t g = 0; g < n; ++g) {
    const float d = float(depths[g]);
    std::memcpy(&key[g], &d, sizeof(float));
  }
#pragma omp parallel for schedule(dynamic, 1) num_threads(n_threads)
  for (int64_t t = 0; t < n_tiles; ++t) {
    std::stable_sort(ids.begin() + offsets[t], ids.begin() + offsets[t + 1],
                     [&key](int64_t a, int64_t b) { return key[a] < key[b]; });
  }
}

void check(const torch::Tensor& means, const torch::Tensor& quats, const torch::Tensor& scales,
           const torch::Tensor& T) {
  const auto n = means.size(0);
  TORCH_CHECK(means.dim() == 2 && means.size(1) == 3, "means must be [N, 3]");
  TORCH_CHECK(quats.dim() == 2 && quats.size(0) == n && quats.size(1) == 4, "quats must be [N, 4]");
  TORCH_CHECK(scales.dim() == 2 && scales.size(0) == n && scales.size(1) == 3,
              "scales must be [N, 3]");
  TORCH_CHECK(T.dim() == 2 && T.size(0) == 4 && T.size(1) == 4, "T_cam_world must be [4, 4]");
  for (const auto* x : {&means, &quats, &scales, &T}) {
    TORCH_CHECK(x->scalar_type() == means.scalar_type(), "all inputs must share a dtype");
    TORCH_CHECK(x->is_contiguous() && x->device().is_cpu(), "inputs must be contiguous CPU");
  }
}

}  // namespace

std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor quats,
                                           torch::Tensor scales, torch::Tensor T, double fx,
                                           double fy, double cx, double cy, int64_t width,
                                           int64_t height, double near) {
  check(means, quats, scales, T);
  const auto n = means.size(0);
  auto opts = means.options();
  auto means2d = torch::empty({n, 2}, opts);
  auto conics = torch::empty({n, 3}, opts);
  auto depths = torch::empty({n}, opts);
  auto radii = torch::empty({n}, opts.dtype(torch::kInt32));
  const Camera cam(fx, fy, cx, cy, int(width), int(height), near);
  const int n_threads = std::max(1, at::get_num_threads());
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_forward", [&] {
    forward_impl<scalar_t>(means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                           scales.data_ptr<scalar_t>(), T.data_ptr<scalar_t>(), cam, n,
                           means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                           depths.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(), n_threads);
  });
  return {means2d, conics, depths, radii};
}

std::vector<torch::Tensor> project_backward(torch::Tensor means, torch::Tensor quats,
                                            torch::Tensor scales, torch::Tensor T, double fx,
                                            double fy, double cx, double cy, int64_t width,
                                            int64_t height, double near, torch::Tensor g_means2d,
                                            torch::Tensor g_conics, torch::Tensor g_depths,
                                            bool want_params) {
  check(means, quats, scales, T);
  const auto n = means.size(0);
  for (const auto* x : {&g_means2d, &g_conics, &g_depths}) {
    TORCH_CHECK(x->scalar_type() == means.scalar_type(), "gradients must share the dtype");
    TORCH_CHECK(x->is_contiguous() && x->device().is_cpu(), "gradients must be contiguous CPU");
  }
  auto opts = means.options();
  // without want_params only d_T is computed; the others come back empty
  const int64_t rows = want_params ? n : 0;
  auto d_means = torch::empty({rows, 3}, opts);
  auto d_quats = torch::empty({rows, 4}, opts);
  auto d_scales = torch::empty({rows, 3}, opts);
  auto d_T = torch::zeros({4, 4}, opts);
  const Camera cam(fx, fy, cx, cy, int(width), int(height), near);
  const int n_threads = std::max(1, at::get_num_threads());
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_backward", [&] {
    std::vector<double> chunk_sums(size_t((n + kChunk - 1) / kChunk) * kPoseSlots);
    backward_impl<scalar_t>(means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                            scales.data_ptr<scalar_t>(), T.data_ptr<scalar_t>(), cam, n,
                            g_means2d.data_ptr<scalar_t>(), g_conics.data_ptr<scalar_t>(),
                            g_depths.data_ptr<scalar_t>(),
                            want_params ? d_means.data_ptr<scalar_t>() : nullptr,
                            want_params ? d_quats.data_ptr<scalar_t>() : nullptr,
                            want_params ? d_scales.data_ptr<scalar_t>() : nullptr,
                            chunk_sums.data(), n_threads);
    double sum[kPoseSlots] = {};
    for (size_t c = 0; c < chunk_sums.size(); c += kPoseSlots) {
      for (int j = 0; j < kPoseSlots; ++j) sum[j] += chunk_sums[c + j];
    }
    scalar_t* dT = d_T.data_ptr<scalar_t>();
    for (int i = 0; i < 3; ++i) {
      for (int k = 0; k < 3; ++k) dT[4 * i + k] = scalar_t(sum[3 * i + k]);
      dT[4 * i + 3] = scalar_t(sum[9 + i]);
    }
  });
  return {d_means, d_quats, d_scales, d_T};
}

std::vector<torch::Tensor> bin_tiles(torch::Tensor means2d, torch::Tensor radii,
                                     torch::Tensor depths, int64_t tiles_x, int64_t tiles_y) {
  const auto n = means2d.size(0);
  TORCH_CHECK(means2d.dim() == 2 && means2d.size(1) == 2, "means2d must be [N, 2]");
  TORCH_CHECK(radii.dim() == 1 && radii.size(0) == n && radii.scalar_type() == torch::kInt32,
              "radii must be [N] int32");
  TORCH_CHECK(depths.dim() == 1 && depths.size(0) == n &&
                  depths.scalar_type() == means2d.scalar_type(),
              "depths must be [N] of the dtype of means2d");
  for (const auto* x : {&means2d, &radii, &depths}) {
    TORCH_CHECK(x->is_contiguous() && x->device().is_cpu(), "inputs must be contiguous CPU");
  }
  auto offsets = torch::empty({tiles_x * tiles_y + 1}, means2d.options().dtype(torch::kInt64));
  std::vector<int64_t> ids;
  const int n_threads = std::max(1, at::get_num_threads());
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "bin_tiles", [&] {
    bin_impl<scalar_t>(means2d.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(),
                       depths.data_ptr<scalar_t>(), n, int(tiles_x), int(tiles_y),
                       offsets.data_ptr<int64_t>(), ids, n_threads);
  });
  auto out = torch::empty({int64_t(ids.size())}, offsets.options());
  if (!ids.empty()) std::memcpy(out.data_ptr<int64_t>(), ids.data(), ids.size() * sizeof(int64_t));
  return {offsets, out};
}
