// The fused CPU raymarcher: one pass per ray over its samples and the boxes its ray hits.
//
// It computes what avatar/raymarch.py's PyTorch fast path computes (same sample placement,
// same trilinear lookup with border clamping, same additive opacity with MVP's early
// termination), but without materialising the (sample, primitive) pairs and their 8 corner
// gathers as tensors: a pair costs a few dozen flops and 8 reads here instead of ~30 tensor
// ops over hundreds of thousands of pairs. Each ray is taken into each candidate box's local
// frame here too (a 3 x 3 matrix and an offset per box), so no [R, K, 3, 3] gather is built.
// The backward pass recomputes each pair's lookup (cheaper than storing it) and writes the
// gradients of the voxel table and of every box's local frame (matrix and offset); PyTorch's
// autograd carries the latter on to the boxes' poses.
//
// Layout (R = rays of the whole batch, K = candidate boxes per ray, S = samples per ray,
// Q = boxes of the whole batch):
//   table      [N, 4]      voxels (r, g, b, density), rows z-major per box (M^3 rows each)
//   lfh        [Q, 3, 3]   local_from_head of each box: y_j = sum_i x_i lfh[i][j] - cl_j
//   cl         [Q, 3]      the box centre in those coordinates
//   prim       [R, K]      box (row of lfh) of each candidate; -1 where the slot is empty
//   ro, rd     [R, 3]      ray origins and unit directions, head space
//   near, far  [R, K]      the candidate box's entry and exit distance along the ray
//   t          [R, S]      sample distances;  dt [R] step length
// A (sample, candidate) pair contributes when near <= t <= far (the same test as the
// PyTorch path, so both keep exactly the same pairs).
//
// Both passes stop a ray at its first sample past opacity 1 (MVP's early termination): every
// later sample has a share of 0 and no gradient, so skipping it changes no bit of the outputs
// (the tensor path computes and multiplies those samples by 0). On a trained head most rays
// saturate, so this skips much of the work. The local frames are computed here too (in
// PyTorch they were a [R, K, 3, 3] gather and two einsums), and `candidates` culls boxes by
// their bounding spheres; docs/experiments.md, section 4, has what each change saved.
//
// Forward runs rays in parallel (each ray writes only its own outputs). Backward runs rays
// in order on one thread: its scatter into the voxel-table gradient is then deterministic.

#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

namespace {

template <typename scalar_t>
struct Lookup {
  int64_t rows[8];
  scalar_t w[8];
  scalar_t f[3];      // fractional position between the two voxel layers, per axis (x, y, z)
  bool free_axis[3];  // the unclamped coordinate lies in [0, m-1]: its gradient passes
  scalar_t rgba[4];
};

// Trilinear lookup at local coordinates y of the M^3 grid whose voxel (0,0,0) is row `base`.
template <typename scalar_t>
inline void lookup(const scalar_t* table, int64_t base, int64_t m, const scalar_t y[3], Lookup<scalar_t>& out) {
  int64_t i0[3];
  for (int a = 0; a < 3; ++a) {
    scalar_t g = (y[a] + scalar_t(1)) * scalar_t(0.5) * scalar_t(m) - scalar_t(0.5);
    out.free_axis[a] = g >= scalar_t(0) && g <= scalar_t(m - 1);
    g = std::min(std::max(g, scalar_t(0)), scalar_t(m - 1));
    int64_t i = static_cast<int64_t>(std::floor(g));
    i = std::min(i, m - 2);
    i0[a] = i;
    out.f[a] = g - scalar_t(i);
  }
  const scalar_t fx = out.f[0], fy = out.f[1], fz = out.f[2];
  const scalar_t wx[2] = {scalar_t(1) - fx, fx};
  const scalar_t wy[2] = {scalar_t(1) - fy, fy};
  const scalar_t wz[2] = {scalar_t(1) - fz, fz};
  for (int c = 0; c < 4; ++c) out.rgba[c] = scalar_t(0);
  int n = 0;
  for (int dz = 0; dz < 2; ++dz)
    for (int dy = 0; dy < 2; ++dy)
      for (int dx = 0; dx < 2; ++dx, ++n) {
        const int64_t row = base + ((i0[2] + dz) * m + (i0[1] + dy)) * m + (i0[0] + dx);
        const scalar_t w = wz[dz] * wy[dy] * wx[dx];
        out.rows[n] = row;
        out.w[n] = w;
        const scalar_t* v = table + row * 4;
        for (int c = 0; c < 4; ++c) out.rgba[c] += w * v[c];
      }
}

// One ray's K candidate boxes: where the ray enters and leaves each, and the ray in its frame.
template <typename scalar_t>
struct RayBoxes {
  int64_t k;
  const scalar_t *near, *far;  // [K]
  std::vector<int64_t> base;   // [K] table row of the box's voxel (0, 0, 0), -1 for an empty slot
  std::vector<scalar_t> o, d;  // [K, 3] the ray's origin and direction in the box's local frame

  explicit RayBoxes(int64_t k_) : k(k_), near(nullptr), far(nullptr), base(k_), o(k_ * 3), d(k_ * 3) {}

  // Ray `ray`'s candidates: y = o + t d in each box's frame, from its lfh and cl rows.
  void load(const scalar_t* lfh, const scalar_t* cl, const int64_t* prim_all, const scalar_t* ro_all,
            const scalar_t* rd_all, const scalar_t* near_all, const scalar_t* far_all, int64_t ray, int64_t m3) {
    near = near_all + ray * k;
    far = far_all + ray * k;
    const int64_t* prim = prim_all + ray * k;
    const scalar_t *ro = ro_all + ray * 3, *rd = rd_all + ray * 3;
    for (int64_t ki = 0; ki < k; ++ki) {
      const int64_t q = prim[ki];
      base[ki] = q < 0 ? -1 : q * m3;
      if (q < 0) continue;
      const scalar_t* mat = lfh + q * 9;
      const scalar_t* c = cl + q * 3;
      for (int j = 0; j < 3; ++j) {
        o[ki * 3 + j] = ro[0] * mat[j] + ro[1] * mat[3 + j] + ro[2] * mat[6 + j] - c[j];
        d[ki * 3 + j] = rd[0] * mat[j] + rd[1] * mat[3 + j] + rd[2] * mat[6 + j];
      }
    }
  }

  // Whether the sample at distance ts lies in box ki (the PyTorch path's test); if so, y = its local position.
  inline bool sample_in(int64_t ki, scalar_t ts, scalar_t y[3]) const {
    if (base[ki] < 0 || ts < near[ki] || ts > far[ki]) return false;
    for (int a = 0; a < 3; ++a) y[a] = o[ki * 3 + a] + ts * d[ki * 3 + a];
    return true;
  }
};

// Density and density-weighted colour of the sample at distance ts, summed over the boxes it is in:
// out = (sigma, sigma * r, sigma * g, sigma * b).
template <typename scalar_t>
inline void sample_sums(const scalar_t* table, const RayBoxes<scalar_t>& boxes, scalar_t ts, int64_t k, int64_t m,
                        scalar_t out[4]) {
  Lookup<scalar_t> lk;
  scalar_t y[3];
  out[0] = out[1] = out[2] = out[3] = 0;
  for (int64_t ki = 0; ki < k; ++ki) {
    if (!boxes.sample_in(ki, ts, y)) continue;
    lookup(table, boxes.base[ki], m, y, lk);
    const scalar_t sk = lk.rgba[3];
    out[0] += sk;
    out[1] += lk.rgba[0] * sk;
    out[2] += lk.rgba[1] * sk;
    out[3] += lk.rgba[2] * sk;
  }
}

// Samples of a ray that can matter: all up to and including the first whose accumulated opacity
// passes 1 (MVP's early termination). Every later sample has `before` > 1, so its share is 0
// and the clamp in the share stops its gradient: it adds nothing to the colour, the gradients
// or the pruning statistics, and skipping it changes no bit of any of them. (A ray that ends
// at exactly 1 keeps all its samples: a later sample's share is then 0 but not clamped.)
template <typename scalar_t>
inline int64_t samples_until_opaque(const scalar_t* sigma, scalar_t step, int64_t s) {
  scalar_t acc = 0;
  for (int64_t si = 0; si < s; ++si) {
    acc += sigma[si] * step;
    if (acc > scalar_t(1)) return si + 1;
  }
  return s;
}

void check_inputs(const torch::Tensor& table, const torch::Tensor& lfh, const torch::Tensor& cl,
                  const torch::Tensor& prim, const torch::Tensor& ro, const torch::Tensor& rd,
                  const torch::Tensor& near, const torch::Tensor& far, const torch::Tensor& t, const torch::Tensor& dt) {
  for (const auto* x : {&table, &lfh, &cl, &prim, &ro, &rd, &near, &far, &t, &dt}) {
    TORCH_CHECK(x->device().is_cpu(), "fused raymarch: CPU tensors only");
    TORCH_CHECK(x->is_contiguous(), "fused raymarch: contiguous tensors only");
  }
  TORCH_CHECK(prim.scalar_type() == torch::kInt64, "fused raymarch: candidate boxes must be int64");
  TORCH_CHECK(table.dim() == 2 && table.size(1) == 4, "fused raymarch: table must be [N, 4]");
  TORCH_CHECK(lfh.dim() == 3 && lfh.size(1) == 3 && lfh.size(2) == 3, "fused raymarch: lfh must be [Q, 3, 3]");
  TORCH_CHECK(cl.dim() == 2 && cl.size(1) == 3 && cl.size(0) == lfh.size(0), "fused raymarch: cl must be [Q, 3]");
  for (const auto* x : {&lfh, &cl, &ro, &rd, &near, &far, &t, &dt})
    TORCH_CHECK(x->scalar_type() == table.scalar_type(), "fused raymarch: all float inputs share one dtype");
}

}  // namespace

// Returns rgb [R, 3], alpha [R], the per-sample sums the backward pass needs (sigma [R, S] and
// sigma_rgb [R, S, 3]) and, if with_added, the opacity each candidate box added to its ray below
// saturation, added [R, K] (else an empty tensor): the pruning statistics' input.
std::vector<torch::Tensor> forward(torch::Tensor table, torch::Tensor lfh, torch::Tensor cl, torch::Tensor prim,
                                   torch::Tensor ro, torch::Tensor rd, torch::Tensor near, torch::Tensor far,
                                   torch::Tensor t, torch::Tensor dt, int64_t m, bool with_added) {
  check_inputs(table, lfh, cl, prim, ro, rd, near, far, t, dt);
  const int64_t r = t.size(0), s = t.size(1), k = prim.size(1), m3 = m * m * m;
  auto opts = table.options();
  auto rgb = torch::zeros({r, 3}, opts);
  auto alpha = torch::zeros({r}, opts);
  auto sigma = torch::zeros({r, s}, opts);
  auto sigma_rgb = torch::zeros({r, s, 3}, opts);
  auto added = with_added ? torch::zeros({r, k}, opts) : torch::empty({0}, opts);
  AT_DISPATCH_FLOATING_TYPES(table.scalar_type(), "fused_raymarch_forward", [&] {
    const scalar_t* tab = table.data_ptr<scalar_t>();
    const scalar_t *lfh_p = lfh.data_ptr<scalar_t>(), *cl_p = cl.data_ptr<scalar_t>();
    const int64_t* prim_p = prim.data_ptr<int64_t>();
    const scalar_t *ro_p = ro.data_ptr<scalar_t>(), *rd_p = rd.data_ptr<scalar_t>();
    const scalar_t *nr_p = near.data_ptr<scalar_t>(), *fr_p = far.data_ptr<scalar_t>();
    const scalar_t *tp = t.data_ptr<scalar_t>(), *dtp = dt.data_ptr<scalar_t>();
    scalar_t *rgb_p = rgb.data_ptr<scalar_t>(), *alpha_p = alpha.data_ptr<scalar_t>();
    scalar_t *sig_p = sigma.data_ptr<scalar_t>(), *srgb_p = sigma_rgb.data_ptr<scalar_t>();
    scalar_t* added_p = with_added ? added.data_ptr<scalar_t>() : nullptr;
    at::parallel_for(0, r, 64, [&](int64_t begin, int64_t end) {
      std::vector<scalar_t> shares(with_added ? s : 0);
      Lookup<scalar_t> lk;
      scalar_t y[3];
      RayBoxes<scalar_t> boxes(k);
      for (int64_t ri = begin; ri < end; ++ri) {
        boxes.load(lfh_p, cl_p, prim_p, ro_p, rd_p, nr_p, fr_p, ri, m3);
        scalar_t* sg = sig_p + ri * s;  // stays 0 past the ray's last sample that matters
        scalar_t* sc = srgb_p + ri * s * 3;
        const scalar_t* t_r = tp + ri * s;
        // MVP's additive compositing: a sample counts with the share of its opacity still below 1.
        const scalar_t step = dtp[ri];
        scalar_t acc = 0, cr = 0, cg = 0, cb = 0;
        int64_t used = s;  // samples up to the first past opacity 1 (samples_until_opaque)
        for (int64_t si = 0; si < s; ++si) {
          scalar_t sums[4];
          sample_sums(tab, boxes, t_r[si], k, m, sums);
          sg[si] = sums[0];
          sc[si * 3] = sums[1];
          sc[si * 3 + 1] = sums[2];
          sc[si * 3 + 2] = sums[3];
          const scalar_t op_s = sg[si] * step;
          const scalar_t q = (scalar_t(1) - acc) / std::max(op_s, scalar_t(1e-10));
          const scalar_t share = std::min(std::max(q, scalar_t(0)), scalar_t(1));
          if (with_added) shares[si] = share;
          const scalar_t w = step * share;
          cr += sc[si * 3] * w;
          cg += sc[si * 3 + 1] * w;
          cb += sc[si * 3 + 2] * w;
          acc += op_s;
          if (acc > scalar_t(1)) {
            used = si + 1;
            break;
          }
        }
        rgb_p[ri * 3] = cr;
        rgb_p[ri * 3 + 1] = cg;
        rgb_p[ri * 3 + 2] = cb;
        alpha_p[ri] = std::min(acc, scalar_t(1));
        if (!with_added) continue;
        // Second pass over the pairs: each box's density times the share of the sample it is in.
        scalar_t* add_r = added_p + ri * k;
        for (int64_t si = 0; si < used; ++si) {
          const scalar_t ts = t_r[si];
          for (int64_t ki = 0; ki < k; ++ki) {
            if (!boxes.sample_in(ki, ts, y)) continue;
            lookup(tab, boxes.base[ki], m, y, lk);
            add_r[ki] += lk.rgba[3] * step * shares[si];
          }
        }
      }
    });
  });
  return {rgb, alpha, sigma, sigma_rgb, added};
}

// Gradients of the voxel table [N, 4] and of the local-frame ray origins and directions [R, K, 3].
// Gradients of the voxel table [N, 4] and of every box's local frame: lfh [Q, 3, 3] and cl [Q, 3].
std::vector<torch::Tensor> backward(torch::Tensor grad_rgb, torch::Tensor grad_alpha, torch::Tensor table,
                                    torch::Tensor lfh, torch::Tensor cl, torch::Tensor prim, torch::Tensor ro,
                                    torch::Tensor rd, torch::Tensor near, torch::Tensor far, torch::Tensor t,
                                    torch::Tensor dt, torch::Tensor sigma, torch::Tensor sigma_rgb, int64_t m) {
  check_inputs(table, lfh, cl, prim, ro, rd, near, far, t, dt);
  grad_rgb = grad_rgb.contiguous();
  grad_alpha = grad_alpha.contiguous();
  const int64_t r = t.size(0), s = t.size(1), k = prim.size(1), m3 = m * m * m;
  auto grad_table = torch::zeros_like(table);
  auto grad_lfh = torch::zeros_like(lfh);
  auto grad_cl = torch::zeros_like(cl);
  AT_DISPATCH_FLOATING_TYPES(table.scalar_type(), "fused_raymarch_backward", [&] {
    const scalar_t* tab = table.data_ptr<scalar_t>();
    const scalar_t *lfh_p = lfh.data_ptr<scalar_t>(), *cl_p = cl.data_ptr<scalar_t>();
    const int64_t* prim_all = prim.data_ptr<int64_t>();
    const scalar_t *ro_all = ro.data_ptr<scalar_t>(), *rd_all = rd.data_ptr<scalar_t>();
    const scalar_t *nr_all = near.data_ptr<scalar_t>(), *fr_all = far.data_ptr<scalar_t>();
    const scalar_t *tp_all = t.data_ptr<scalar_t>(), *dtp = dt.data_ptr<scalar_t>();
    const scalar_t *sig_all = sigma.data_ptr<scalar_t>(), *srgb_all = sigma_rgb.data_ptr<scalar_t>();
    const scalar_t *g_rgb = grad_rgb.data_ptr<scalar_t>(), *g_alpha = grad_alpha.data_ptr<scalar_t>();
    scalar_t* g_tab = grad_table.data_ptr<scalar_t>();
    scalar_t *g_lfh = grad_lfh.data_ptr<scalar_t>(), *g_cl = grad_cl.data_ptr<scalar_t>();
    std::vector<scalar_t> before(s), g_sigma(s), g_c(s * 3), g_o(k * 3), g_d(k * 3);
    Lookup<scalar_t> lk;
    RayBoxes<scalar_t> boxes(k);
    for (int64_t ri = 0; ri < r; ++ri) {
      const scalar_t* sg = sig_all + ri * s;
      const scalar_t* sc = srgb_all + ri * s * 3;
      const scalar_t step = dtp[ri];
      const scalar_t gr[3] = {g_rgb[ri * 3], g_rgb[ri * 3 + 1], g_rgb[ri * 3 + 2]};
      scalar_t acc = 0;
      for (int64_t si = 0; si < s; ++si) {
        before[si] = acc;
        acc += sg[si] * step;
      }
      // d loss / d opacity_j: from alpha (if not clamped), from sample j's own share, and from
      // the share of every later sample through its `before` (a suffix sum).
      const scalar_t g_acc = acc <= scalar_t(1) ? g_alpha[ri] : scalar_t(0);
      const int64_t used = samples_until_opaque(sg, step, s);  // later samples: no gradient at all
      scalar_t later = 0;  // sum over samples after j of d loss / d before
      for (int64_t si = used - 1; si >= 0; --si) {
        const scalar_t op_s = sg[si] * step;
        const scalar_t denom = std::max(op_s, scalar_t(1e-10));
        const scalar_t q = (scalar_t(1) - before[si]) / denom;
        const scalar_t share = std::min(std::max(q, scalar_t(0)), scalar_t(1));
        for (int c = 0; c < 3; ++c) g_c[si * 3 + c] = gr[c] * step * share;
        const scalar_t g_share = step * (gr[0] * sc[si * 3] + gr[1] * sc[si * 3 + 1] + gr[2] * sc[si * 3 + 2]);
        const scalar_t g_q = (q >= scalar_t(0) && q <= scalar_t(1)) ? g_share : scalar_t(0);
        const scalar_t g_op_own = op_s >= scalar_t(1e-10) ? -g_q * (scalar_t(1) - before[si]) / (denom * denom)
                                                          : scalar_t(0);
        g_sigma[si] = (g_op_own + later + g_acc) * step;
        later += -g_q / denom;
      }
      boxes.load(lfh_p, cl_p, prim_all, ro_all, rd_all, nr_all, fr_all, ri, m3);
      std::fill(g_o.begin(), g_o.end(), scalar_t(0));
      std::fill(g_d.begin(), g_d.end(), scalar_t(0));
      const scalar_t* tp = tp_all + ri * s;
      scalar_t y[3];
      for (int64_t si = 0; si < used; ++si) {
        const scalar_t ts = tp[si];
        const scalar_t* gc = g_c.data() + si * 3;
        for (int64_t ki = 0; ki < k; ++ki) {
          if (!boxes.sample_in(ki, ts, y)) continue;
          lookup(tab, boxes.base[ki], m, y, lk);
          const scalar_t sk = lk.rgba[3];
          // sigma_rgb += rgb_k * sigma_k and sigma += sigma_k.
          const scalar_t g_rgba[4] = {gc[0] * sk, gc[1] * sk, gc[2] * sk,
                                      g_sigma[si] + gc[0] * lk.rgba[0] + gc[1] * lk.rgba[1] + gc[2] * lk.rgba[2]};
          scalar_t g_w[8];
          for (int n = 0; n < 8; ++n) {
            scalar_t* gt = g_tab + lk.rows[n] * 4;
            const scalar_t* v = tab + lk.rows[n] * 4;
            scalar_t gw = 0;
            for (int c = 0; c < 4; ++c) {
              gt[c] += lk.w[n] * g_rgba[c];
              gw += g_rgba[c] * v[c];
            }
            g_w[n] = gw;
          }
          // w[n] = wz * wy * wx with corner n = (dz, dy, dx) and w*(0) = 1 - f, w*(1) = f.
          const scalar_t fx = lk.f[0], fy = lk.f[1], fz = lk.f[2];
          const scalar_t wx[2] = {scalar_t(1) - fx, fx}, wy[2] = {scalar_t(1) - fy, fy},
                         wz[2] = {scalar_t(1) - fz, fz};
          scalar_t g_f[3] = {0, 0, 0};
          int n = 0;
          for (int dz = 0; dz < 2; ++dz)
            for (int dy = 0; dy < 2; ++dy)
              for (int dx = 0; dx < 2; ++dx, ++n) {
                const scalar_t sx = dx ? scalar_t(1) : scalar_t(-1);
                const scalar_t sy = dy ? scalar_t(1) : scalar_t(-1);
                const scalar_t sz = dz ? scalar_t(1) : scalar_t(-1);
                g_f[0] += g_w[n] * wz[dz] * wy[dy] * sx;
                g_f[1] += g_w[n] * wz[dz] * sy * wx[dx];
                g_f[2] += g_w[n] * sz * wy[dy] * wx[dx];
              }
          for (int a = 0; a < 3; ++a) {
            if (!lk.free_axis[a]) continue;  // clamped at the border: no gradient, as torch.clamp
            const scalar_t g_y = g_f[a] * scalar_t(0.5) * scalar_t(m);
            g_o[ki * 3 + a] += g_y;
            g_d[ki * 3 + a] += ts * g_y;
          }
        }
      }
      // The ray in box q's frame is o_j = sum_i ro_i lfh[i][j] - cl_j, d_j = sum_i rd_i lfh[i][j].
      const int64_t* prim_r = prim_all + ri * k;
      const scalar_t *o = ro_all + ri * 3, *d = rd_all + ri * 3;
      for (int64_t ki = 0; ki < k; ++ki) {
        const int64_t q = prim_r[ki];
        if (q < 0) continue;
        scalar_t* gm = g_lfh + q * 9;
        for (int i = 0; i < 3; ++i)
          for (int j = 0; j < 3; ++j) gm[i * 3 + j] += o[i] * g_o[ki * 3 + j] + d[i] * g_d[ki * 3 + j];
        for (int j = 0; j < 3; ++j) g_cl[q * 3 + j] -= g_o[ki * 3 + j];
      }
    }
  });
  return {grad_table, grad_lfh, grad_cl};
}

// The boxes each ray hits, in box order: cand [R, K] (box index within the ray's batch item, -1
// for an empty slot; K = the most boxes any ray hits, at least 1), their entry and exit distances
// near, far [R, K], and the ray's span t_min, t_max [R] over them (0, 0 for a ray that hits
// none). The slab test is the one of avatar.raymarch.box_intervals.
// A box whose bounding sphere (centre, radius) the ray's line misses is skipped before the slab
// test: a ray hits ~30 of the tiny head's 256 boxes, and the sphere test costs a third of the slab
// test. The radius is padded by 0.1% so that rounding never culls a box the slab test would keep.
//   rays_o, rays_d [B, Rb, 3]; local_from_head [B, P, 3, 3]; centre_local, centre [B, P, 3]; radius [B, P]
std::vector<torch::Tensor> candidates(torch::Tensor rays_o, torch::Tensor rays_d, torch::Tensor local_from_head,
                                      torch::Tensor centre_local, torch::Tensor centre, torch::Tensor radius) {
  for (const auto* x : {&rays_o, &rays_d, &local_from_head, &centre_local, &centre, &radius}) {
    TORCH_CHECK(x->device().is_cpu() && x->is_contiguous(), "fused raymarch: contiguous CPU tensors only");
    TORCH_CHECK(x->scalar_type() == rays_o.scalar_type(), "fused raymarch: all inputs share one dtype");
  }
  const int64_t b = rays_o.size(0), rb = rays_o.size(1), p = local_from_head.size(1), r = b * rb;
  auto opts = rays_o.options();
  // Each ray's hits go to a row of `cap` slots, left uninitialised. Rows of P slots, filled, made
  // three [R, P] scratch tensors, up to 134 MB (float32) for each chunk of avatar.raymarch's 2^23
  // (ray, box) pairs, while a ray hits a few dozen boxes (at most 38 of 256 on the
  // initial tiny head); on tiny the fills cost 0.2 ms a training step. A ray that hits more than
  // `cap` boxes makes the scan run again with rows of P slots: a hit is never dropped.
  const int64_t cap = std::min<int64_t>(p, 64);
  auto counts = torch::zeros({r}, opts.dtype(torch::kInt64));
  auto t_min = torch::zeros({r}, opts);
  auto t_max = torch::zeros({r}, opts);
  torch::Tensor all_cand, all_near, all_far;
  auto scan = [&](int64_t width) {
    all_cand = torch::empty({r, width}, opts.dtype(torch::kInt64));
    all_near = torch::empty({r, width}, opts);
    all_far = torch::empty({r, width}, opts);
    AT_DISPATCH_FLOATING_TYPES(rays_o.scalar_type(), "fused_raymarch_candidates", [&] {
      const scalar_t *ro = rays_o.data_ptr<scalar_t>(), *rd = rays_d.data_ptr<scalar_t>();
      const scalar_t *lfh = local_from_head.data_ptr<scalar_t>(), *cl = centre_local.data_ptr<scalar_t>();
      const scalar_t *ctr = centre.data_ptr<scalar_t>(), *rad = radius.data_ptr<scalar_t>();
      int64_t* cand_p = all_cand.data_ptr<int64_t>();
      scalar_t *near_p = all_near.data_ptr<scalar_t>(), *far_p = all_far.data_ptr<scalar_t>();
      int64_t* count_p = counts.data_ptr<int64_t>();
      scalar_t *tmin_p = t_min.data_ptr<scalar_t>(), *tmax_p = t_max.data_ptr<scalar_t>();
      const scalar_t tiny = scalar_t(1e-12);
      at::parallel_for(0, r, 64, [&](int64_t begin, int64_t end) {
        for (int64_t ri = begin; ri < end; ++ri) {
          const int64_t bi = ri / rb;
          const scalar_t* o = ro + ri * 3;
          const scalar_t* d = rd + ri * 3;
          const scalar_t dd = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
          int64_t n = 0;
          scalar_t lo = std::numeric_limits<scalar_t>::max(), hi = std::numeric_limits<scalar_t>::lowest();
          for (int64_t pi = 0; pi < p; ++pi) {
            // Squared distance from the box centre to the ray's line: |w|^2 - (w.d)^2 / |d|^2.
            const scalar_t* cw = ctr + (bi * p + pi) * 3;
            const scalar_t w0 = cw[0] - o[0], w1 = cw[1] - o[1], w2 = cw[2] - o[2];
            const scalar_t wd = w0 * d[0] + w1 * d[1] + w2 * d[2];
            const scalar_t bound = rad[bi * p + pi] * scalar_t(1.001);
            if (w0 * w0 + w1 * w1 + w2 * w2 - wd * wd / dd > bound * bound) continue;
            const scalar_t* mat = lfh + (bi * p + pi) * 9;  // y_j = sum_i x_i mat[i][j] - c_j
            const scalar_t* c = cl + (bi * p + pi) * 3;
            scalar_t t_near = std::numeric_limits<scalar_t>::lowest(), t_far = std::numeric_limits<scalar_t>::max();
            for (int j = 0; j < 3; ++j) {
              const scalar_t oj = o[0] * mat[j] + o[1] * mat[3 + j] + o[2] * mat[6 + j] - c[j];
              scalar_t dj = d[0] * mat[j] + d[1] * mat[3 + j] + d[2] * mat[6 + j];
              if (std::abs(dj) < tiny) dj = std::copysign(tiny, dj);
              const scalar_t inv = scalar_t(1) / dj;
              const scalar_t mid = -oj * inv, reach = std::abs(inv);
              t_near = std::max(t_near, mid - reach);
              t_far = std::min(t_far, mid + reach);
            }
            t_near = std::max(t_near, scalar_t(0));
            if (!(t_far > t_near)) continue;
            if (n < width) {
              cand_p[ri * width + n] = pi;
              near_p[ri * width + n] = t_near;
              far_p[ri * width + n] = t_far;
            }
            ++n;
            lo = std::min(lo, t_near);
            hi = std::max(hi, t_far);
          }
          count_p[ri] = n;
          tmin_p[ri] = n ? lo : scalar_t(0);
          tmax_p[ri] = n ? hi : scalar_t(0);
        }
      });
    });
  };
  scan(cap);
  const int64_t k = std::max<int64_t>(1, r ? counts.max().item<int64_t>() : 1);
  int64_t width = cap;
  if (k > cap) {
    scan(p);
    width = p;
  }
  // The [R, K] result: each ray's hits, then empty slots (-1, 0, 0).
  auto cand = torch::empty({r, k}, opts.dtype(torch::kInt64));
  auto near = torch::empty({r, k}, opts);
  auto far = torch::empty({r, k}, opts);
  AT_DISPATCH_FLOATING_TYPES(rays_o.scalar_type(), "fused_raymarch_candidates_pack", [&] {
    const int64_t* src_c = all_cand.data_ptr<int64_t>();
    const scalar_t *src_n = all_near.data_ptr<scalar_t>(), *src_f = all_far.data_ptr<scalar_t>();
    int64_t* dst_c = cand.data_ptr<int64_t>();
    scalar_t *dst_n = near.data_ptr<scalar_t>(), *dst_f = far.data_ptr<scalar_t>();
    const int64_t* count_p = counts.data_ptr<int64_t>();
    at::parallel_for(0, r, 256, [&](int64_t begin, int64_t end) {
      for (int64_t ri = begin; ri < end; ++ri) {
        const int64_t n = count_p[ri];
        std::copy(src_c + ri * width, src_c + ri * width + n, dst_c + ri * k);
        std::copy(src_n + ri * width, src_n + ri * width + n, dst_n + ri * k);
        std::copy(src_f + ri * width, src_f + ri * width + n, dst_f + ri * k);
        std::fill(dst_c + ri * k + n, dst_c + (ri + 1) * k, int64_t(-1));
        std::fill(dst_n + ri * k + n, dst_n + (ri + 1) * k, scalar_t(0));
        std::fill(dst_f + ri * k + n, dst_f + (ri + 1) * k, scalar_t(0));
      }
    });
  });
  return {cand, near, far, t_min, t_max};
}

// The GIL is released while a kernel runs: two models trained side by side in two threads
// (stages/train/side_by_side.py) then overlap here as they do in torch's own kernels.
PYBIND11_MODULE(TORCH_EXTENSION_NAME, module) {
  using release = pybind11::call_guard<pybind11::gil_scoped_release>;
  module.def("forward", &forward, "fused raymarch, forward", release());
  module.def("backward", &backward, "fused raymarch, backward", release());
  module.def("candidates", &candidates, "the boxes each ray hits (slab test)", release());
}
