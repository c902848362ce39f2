// The renderer's image without derivatives, as one XLA FFI custom call on the CPU.
//
// The same arithmetic as twinrl/render/renderer.py's Renderer._render and primitives.py (read
// those for the why of each step): rays from a pinhole camera, each drawn primitive's first hit
// and (soft image) closest approach and normal in its local frame, per-pixel culling of crowded
// types, the `layers` most covering surfaces, front-to-back compositing with a smooth depth
// order, hard shadow rays and OpenGL's fixed-function shading. XLA runs the JAX version as
// hundreds of passes over (pixel, surface) arrays; here each pixel is drawn start to finish in
// registers, the frames' rows split across the CPU's cores. Derivatives stay with the JAX
// version (renderer.py's custom JVP): this kernel is only ever the primal of a render nobody
// differentiates. Meshes are not drawn here (the Python side falls back to JAX for them).
//
// What it skips leaves the image as JAX draws it: a ray that misses a geom's bounding sphere is
// not intersected with it; a surface is shaded only where it adds to the pixel (weight > 1e-12);
// a soft silhouette 30 tau pixels away (coverage < 1e-13) is not searched for. The hard image
// and shadow rays test every geom, where JAX culls crowded types to the nearest few (exact
// wherever those hold the first hit, resp. the occluder; culling only ever drops soft coverage).
//
// Inputs: cam (..., 15) = pos (3), xmat (9, row-major; columns right, up, back), pixel size at
// unit depth, principal column and row; geo (..., G, 19) = xpos (3), xmat (9), size (3), albedo
// rgba (4), the renderer's geoms in its order. Outputs: rgb (..., H, W, 3), depth (..., H, W),
// segmentation and body ids (..., H, W) int32, weights (..., H, W, G), background (..., H, W).

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <limits>
#include <thread>
#include <vector>

#if defined(__linux__)
#include <sched.h>
#endif

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

constexpr int kLightStride = 22;  // type, pos 3, dir 3, ambient 3, diffuse 3, specular 3,
                                  // cutoff, exponent, attenuation 3, castshadow

template <typename T>
struct K {
  static constexpr T eps = T(1e-12);
  static T inf() { return std::numeric_limits<T>::infinity(); }
};

template <typename T>
inline T dot3(const T* a, const T* b) { return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]; }

template <typename T>
inline T safe_div(T a, T b) {
  T e = K<T>::eps;
  return a / (std::fabs(b) > e ? b : (b < 0 ? -e : e));
}

template <typename T>
inline T first_positive(T c) { return c > 0 ? c : K<T>::inf(); }

template <typename T>
inline T sigmoid(T x) { return T(1) / (T(1) + std::exp(-x)); }

// p_loc = (v - xpos) @ xmat, or v @ xmat for directions
template <typename T>
inline void to_local(const T* v, const T* m, T* out) {
  for (int j = 0; j < 3; ++j) out[j] = (v[0] * m[j] + v[1] * m[3 + j]) + v[2] * m[6 + j];
}
template <typename T>
inline void to_world(const T* v, const T* m, T* out) {
  for (int i = 0; i < 3; ++i) out[i] = (v[0] * m[3 * i] + v[1] * m[3 * i + 1]) + v[2] * m[3 * i + 2];
}

// ------------------------------------------------------------------ first hits (local frame)
// the nearer of the line's two parameters at distance `rad` from the origin (n: 2 or 3 axes);
// false where it passes further away
template <typename T>
inline bool line_root(const T* o, const T* r, int n, T rad, T& s0) {
  T A = n == 3 ? dot3(r, r) : r[0] * r[0] + r[1] * r[1];
  T B = n == 3 ? dot3(o, r) : o[0] * r[0] + o[1] * r[1];
  A = A > K<T>::eps ? A : K<T>::eps;
  T f = B / A, ll = 0;
  for (int k = 0; k < n; ++k) {
    T lc = o[k] - f * r[k];
    ll = k == 0 ? lc * lc : ll + lc * lc;
  }
  T disc = A * (rad * rad - ll);
  T sq = disc > 0 ? std::sqrt(disc) : T(0);
  s0 = (-B - sq) / A;
  return disc >= 0;
}

template <typename T>
inline T hit_sphere(const T* o, const T* r, T rad) {
  T s0;
  bool ok = line_root(o, r, 3, rad, s0);
  return ok ? first_positive(s0) : K<T>::inf();
}

template <typename T>
inline T hit_tube(const T* o, const T* r, T rad, T h) {
  T s0;
  bool ok = line_root(o, r, 2, rad, s0);
  T z = o[2] + s0 * r[2];
  bool good = ok && std::fabs(z) <= h && (r[0] * r[0] + r[1] * r[1]) > K<T>::eps;
  return good ? first_positive(s0) : K<T>::inf();
}

template <typename T>
T hit(int type, const T* o, const T* r, const T* sz) {
  const T inf = K<T>::inf();
  switch (type) {
    case 0: {  // plane z = 0, front side, finite rectangle where sizes > 0
      T s = safe_div(-o[2], r[2]);
      T px = o[0] + s * r[0], py = o[1] + s * r[1];
      bool in = (sz[0] > 0 ? std::fabs(px) <= sz[0] : true) &&
                (sz[1] > 0 ? std::fabs(py) <= sz[1] : true);
      return (o[2] > 0 && r[2] < 0 && in && s > 0) ? s : inf;
    }
    case 2:
      return hit_sphere(o, r, sz[0]);
    case 3: {
      T rad = sz[0], h = sz[1];
      T side = hit_tube(o, r, rad, h);
      T ot[3] = {o[0], o[1], o[2] - h}, ob[3] = {o[0], o[1], o[2] + h};
      return std::min(side, std::min(hit_sphere(ot, r, rad), hit_sphere(ob, r, rad)));
    }
    case 4: {
      T os[3], rs[3];
      for (int k = 0; k < 3; ++k) os[k] = o[k] / sz[k], rs[k] = r[k] / sz[k];
      return hit_sphere(os, rs, T(1));
    }
    case 5: {
      T rad = sz[0], h = sz[1];
      T side = hit_tube(o, r, rad, h), caps = inf;
      for (int k = 0; k < 2; ++k) {
        T sign = k == 0 ? T(1) : T(-1);
        T s = safe_div(sign * h - o[2], r[2]);
        T px = o[0] + s * r[0], py = o[1] + s * r[1];
        bool in = px * px + py * py <= rad * rad;
        caps = std::min(caps, in ? first_positive(s) : inf);
      }
      return std::min(side, caps);
    }
    case 6: {
      T tmin = 0, tmax = 0;
      for (int k = 0; k < 3; ++k) {
        T t1 = safe_div(-sz[k] - o[k], r[k]), t2 = safe_div(sz[k] - o[k], r[k]);
        T lo = std::min(t1, t2), hi = std::max(t1, t2);
        tmin = k == 0 ? lo : std::max(tmin, lo);
        tmax = k == 0 ? hi : std::min(tmax, hi);
      }
      return (tmin <= tmax && tmin > 0) ? tmin : inf;
    }
  }
  return inf;
}

// ------------------------------------------------------------------ closest approaches
template <typename T>
inline void line_segment(const T* o, const T* r, const T* a, const T* b, T& s, T& d) {
  T rr = dot3(r, r);
  T e[3], am[3];
  for (int k = 0; k < 3; ++k) e[k] = b[k] - a[k], am[k] = a[k] - o[k];
  T s0 = dot3(am, r) / rr;
  T ds = dot3(e, r) / rr;
  T u[3], v[3];
  for (int k = 0; k < 3; ++k) u[k] = o[k] + s0 * r[k] - a[k], v[k] = ds * r[k] - e[k];
  T vv = dot3(v, v);
  T z = -dot3(u, v) / std::max(vv, K<T>::eps);
  z = std::min(std::max(z, T(0)), T(1));
  T p[3];
  for (int k = 0; k < 3; ++k) p[k] = u[k] + z * v[k];
  s = s0 + ds * z;
  d = std::sqrt(dot3(p, p) + T(1e-20));
}

template <typename T>
inline T sdf_cylinder(const T* p, T rad, T h) {
  T rxy = std::sqrt(p[0] * p[0] + p[1] * p[1] + T(1e-20));
  T q0 = rxy - rad, q1 = std::fabs(p[2]) - h;
  T a = std::max(q0, T(0)), b = std::max(q1, T(0));
  return std::min(std::max(q0, q1), T(0)) + std::sqrt(a * a + b * b + T(1e-20));
}

// the 12 edges of [-1, 1]^3: for each axis, the four (s1, s2) sign pairs of the other two
struct BoxEdges {
  double a[12][3], e[12][3];
  BoxEdges() {
    int n = 0;
    for (int axis = 0; axis < 3; ++axis) {
      int o0 = axis == 0 ? 1 : 0, o1 = axis == 2 ? 1 : 2;
      for (int i = 0; i < 2; ++i)
        for (int j = 0; j < 2; ++j, ++n) {
          double lo[3] = {0, 0, 0};
          lo[o0] = i ? 1.0 : -1.0;
          lo[o1] = j ? 1.0 : -1.0;
          lo[axis] = -1.0;
          for (int k = 0; k < 3; ++k) a[n][k] = lo[k], e[n][k] = k == axis ? 2.0 : 0.0;
        }
    }
  }
};
const BoxEdges kBox;

template <typename T>
void closest(int type, const T* o, const T* r, const T* sz, int iters, T& s, T& d) {
  const T inf = K<T>::inf();
  switch (type) {
    case 0: {
      T sp = safe_div(-o[2], r[2]);
      T px = o[0] + sp * r[0], py = o[1] + sp * r[1];
      bool front = o[2] > 0 && r[2] < 0;
      T qx = std::fabs(px) - sz[0], qy = std::fabs(py) - sz[1];
      bool finite = sz[0] > 0 && sz[1] > 0;
      T a = std::max(qx, T(0)), b = std::max(qy, T(0));
      T dd = std::min(std::max(qx, qy), T(0)) + std::sqrt(a * a + b * b + T(1e-20));
      dd = finite ? dd : T(-1e3);
      s = front ? sp : inf;
      d = front ? dd : T(1e3);
      return;
    }
    case 2: {
      T rr = dot3(r, r);
      s = -dot3(o, r) / rr;
      T p[3];
      for (int k = 0; k < 3; ++k) p[k] = o[k] + s * r[k];
      d = std::sqrt(dot3(p, p) + T(1e-20)) - sz[0];
      return;
    }
    case 4: {
      T os[3], rs[3], one[3] = {1, 1, 1};
      for (int k = 0; k < 3; ++k) os[k] = o[k] / sz[k], rs[k] = r[k] / sz[k];
      closest<T>(2, os, rs, one, iters, s, d);
      d = d * (((sz[0] + sz[1]) + sz[2]) / T(3));
      return;
    }
    case 3: {
      T a[3] = {0, 0, -sz[1]}, b[3] = {0, 0, sz[1]};
      line_segment(o, r, a, b, s, d);
      d -= sz[0];
      return;
    }
    case 5: {
      T rad = sz[0], h = sz[1];
      T rb = std::sqrt(rad * rad + h * h);
      T rr = dot3(r, r);
      T sc = -dot3(o, r) / rr;
      T half = rb / std::sqrt(rr) * T(1.05) + T(1e-6);
      T lo = std::max(sc - half, T(1e-6)), hi = std::max(sc + half, T(2e-6));
      const T g = T(0.6180339887498949);
      auto f = [&](T t) {
        T p[3] = {o[0] + t * r[0], o[1] + t * r[1], o[2] + t * r[2]};
        return sdf_cylinder(p, rad, h);
      };
      T c = hi - g * (hi - lo), dd = lo + g * (hi - lo);
      T fc = f(c), fd = f(dd);
      for (int it = 0; it < iters; ++it) {
        bool left = fc < fd;
        hi = left ? dd : hi;
        lo = left ? lo : c;
        T nc = left ? hi - g * (hi - lo) : dd;
        T nd = left ? c : lo + g * (hi - lo);
        T fx = f(left ? nc : nd);
        T fc2 = left ? fx : fd, fd2 = left ? fc : fx;
        fc = fc2, fd = fd2, c = nc, dd = nd;
      }
      s = T(0.5) * (lo + hi);
      d = f(s);
      return;
    }
    case 6: {
      // inside: the deepest point (box_depth); outside: the nearest edge
      T A[3], P[3], Q[3];
      for (int k = 0; k < 3; ++k) {
        T sg = r[k] >= 0 ? T(1) : T(-1);
        A[k] = sg * r[k];
        P[k] = sg * o[k] - sz[k];
        Q[k] = -sg * o[k] - sz[k];
      }
      T best_v = 0, best_s = 0;
      int bi = 0, bj = 0;
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
          T den = A[i] + A[j];
          bool ok = den > 0;
          den = ok ? den : T(1);
          T v = ok ? (A[i] * Q[j] + A[j] * P[i]) / den : -inf;
          T sv = (Q[j] - P[i]) / den;
          if (i == 0 && j == 0) {
            best_v = v, best_s = sv;
          } else if (v > best_v) {
            best_v = v, best_s = sv, bi = i, bj = j;
          }
        }
      T d_in = (A[bi] * Q[bj] + A[bj] * P[bi]) / (A[bi] + A[bj]);
      if (d_in < 0) {
        s = best_s, d = d_in;
        return;
      }
      T rr = dot3(r, r), irr = T(1) / rr;
      int best_k = 0;
      T best_d = inf;
      for (int k = 0; k < 12; ++k) {
        T a[3], e[3];
        for (int i = 0; i < 3; ++i) a[i] = T(kBox.a[k][i]) * sz[i], e[i] = T(kBox.e[k][i]) * sz[i];
        T s0 = ((a[0] - o[0]) * r[0] + (a[1] - o[1]) * r[1] + (a[2] - o[2]) * r[2]) * irr;
        T ds = (e[0] * r[0] + e[1] * r[1] + e[2] * r[2]) * irr;
        T u[3], v[3];
        for (int i = 0; i < 3; ++i) u[i] = o[i] + s0 * r[i] - a[i], v[i] = ds * r[i] - e[i];
        T vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
        T uv = u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
        T z = std::min(std::max(-uv / std::max(vv, K<T>::eps), T(0)), T(1));
        T x0 = u[0] + z * v[0], x1 = u[1] + z * v[1], x2 = u[2] + z * v[2];
        T dd = x0 * x0 + x1 * x1 + x2 * x2;
        if (dd < best_d) best_d = dd, best_k = k;
      }
      T a[3], b[3];
      for (int i = 0; i < 3; ++i) {
        a[i] = T(kBox.a[best_k][i]) * sz[i];
        b[i] = a[i] + T(kBox.e[best_k][i]) * sz[i];
      }
      line_segment(o, r, a, b, s, d);
      return;
    }
  }
  s = inf, d = T(1e3);
}

// unnormalised outward normal at local p; soft: faces blended over tn metres, else the nearest
template <typename T>
void normal(int type, const T* p, const T* sz, bool soft, T tn, T* n) {
  switch (type) {
    case 0:
      n[0] = 0, n[1] = 0, n[2] = 1;
      return;
    case 2:
      n[0] = p[0], n[1] = p[1], n[2] = p[2];
      return;
    case 3: {
      T z = std::min(std::max(p[2], -sz[1]), sz[1]);
      n[0] = p[0], n[1] = p[1], n[2] = p[2] - z;
      return;
    }
    case 4:
      for (int k = 0; k < 3; ++k) n[k] = p[k] / (sz[k] * sz[k]);
      return;
    case 5: {
      T rxy = std::sqrt(p[0] * p[0] + p[1] * p[1] + T(1e-20));
      T dr = std::fabs(rxy - sz[0]), dz = std::fabs(std::fabs(p[2]) - sz[1]);
      T w_cap = soft ? sigmoid((dr - dz) / tn) : T(dz < dr ? 1 : 0);
      T side = (T(1) - w_cap) / rxy;
      n[0] = side * p[0], n[1] = side * p[1], n[2] = w_cap * (p[2] >= 0 ? T(1) : T(-1));
      return;
    }
    case 6: {
      T d[3], w[3];
      for (int k = 0; k < 3; ++k) d[k] = std::fabs(std::fabs(p[k]) - sz[k]);
      if (soft) {
        T lo = std::min(std::min(d[0], d[1]), d[2]);
        T e[3];
        for (int k = 0; k < 3; ++k) e[k] = std::exp((lo - d[k]) / tn);
        T tot = (e[0] + e[1]) + e[2];
        for (int k = 0; k < 3; ++k) w[k] = e[k] / tot;
      } else {
        bool k0 = d[0] <= d[1] && d[0] <= d[2];
        bool k1 = !k0 && d[1] <= d[2];
        w[0] = k0, w[1] = k1, w[2] = !k0 && !k1;
      }
      for (int k = 0; k < 3; ++k) n[k] = w[k] * (p[k] >= 0 ? T(1) : T(-1));
      return;
    }
  }
  n[0] = 0, n[1] = 0, n[2] = 1;
}

// A sphere around a primitive (local frame, centred): its radius, or 0 for a plane (unbounded)
template <typename T>
inline T bound_radius(int t, const T* sz) {
  switch (t) {
    case 2: return sz[0];
    case 3: return sz[0] + sz[1];
    case 4: return std::max(std::max(sz[0], sz[1]), sz[2]);
    case 5: return std::sqrt(sz[0] * sz[0] + sz[1] * sz[1]);
    case 6: return std::sqrt(dot3(sz, sz));
  }
  return T(0);
}

// How far (m) the line o + s r passes outside the bounding sphere (<= 0: it passes through), with
// a margin for rounding: a ray with a positive gap cannot hit the geom.
template <typename T>
inline T bound_gap(const T* o, const T* r, T rb) {
  T rr = dot3(r, r), orr = dot3(o, r);
  return std::sqrt(std::max(dot3(o, o) - orr * orr / rr, T(0))) - rb * T(1.001) - T(1e-6);
}

// Whether the soft silhouette of a geom whose bounding sphere the ray misses by `gap` lies
// further than `margin` pixels away at any depth its closest approach can have: coverage there
// is below sigmoid(-margin / tau). (Not for ellipsoids, whose closest approach is taken in a
// scaled frame.)
template <typename T>
inline bool far_from(int t, const T* o, const T* r, T rb, T gap, T px, T near_, T margin) {
  if (t == 0 || t == 4 || !(gap > 0)) return false;
  T rr = dot3(r, r);
  T s_max = -dot3(o, r) / rr + rb / std::sqrt(rr) * T(1.05) + T(1e-6);
  return gap > margin * std::max(s_max, near_) * px;
}

// lax.top_k's indices: the k largest of x[0..n), largest first, ties to the lower index
template <typename T>
inline void top_k(const T* x, int n, int k, int* out) {
  uint64_t taken = 0;  // n <= 64
  for (int q = 0; q < k; ++q) {
    int best = -1;
    for (int j = 0; j < n; ++j)
      if (!((taken >> j) & 1) && (best < 0 || x[j] > x[best])) best = j;
    out[q] = best;
    taken |= uint64_t(1) << best;
  }
}

// ------------------------------------------------------------------ the scene
struct Config {
  ffi::Span<const int32_t> types, gids, bodies, opts;
  ffi::Span<const double> mat, lights, headlight, scal;
};

template <typename T>
struct Scene {
  int G, NL;
  int iters, per_pixel, cull_above, layers;
  bool shadows;
  T near_, far_, far_depth, tau, gamma;
  std::vector<int> types, gids, bodies;
  std::vector<T> spec, shin, emis;            // per geom
  std::vector<T> light;                        // NL x kLightStride
  std::vector<T> cutoff_cos;                   // per light, cos of the spot's cutoff
  bool head_on;
  T head[9];
  std::vector<std::pair<int, std::vector<int>>> groups;  // (type, renderer indices)
  int slots;                                   // surfaces per pixel
  bool any_shadow;

  explicit Scene(const Config& c) {
    G = int(c.types.size());
    types.assign(c.types.begin(), c.types.end());
    gids.assign(c.gids.begin(), c.gids.end());
    bodies.assign(c.bodies.begin(), c.bodies.end());
    for (int g = 0; g < G; ++g) {
      spec.push_back(T(c.mat[3 * g])), shin.push_back(T(c.mat[3 * g + 1]));
      emis.push_back(T(c.mat[3 * g + 2]));
    }
    NL = int(c.lights.size()) / kLightStride;
    for (double x : c.lights) light.push_back(T(x));
    for (int i = 0; i < NL; ++i)
      cutoff_cos.push_back(T(std::cos(c.lights[i * kLightStride + 16] * M_PI / 180.0)));
    head_on = c.headlight[0] != 0;
    for (int k = 0; k < 9; ++k) head[k] = T(c.headlight[1 + k]);
    near_ = T(c.scal[0]), far_ = T(c.scal[1]), far_depth = T(c.scal[2]);
    tau = T(c.scal[3]), gamma = T(c.scal[4]);
    iters = c.opts[0], per_pixel = c.opts[1], cull_above = c.opts[2], layers = c.opts[3];
    shadows = c.opts[4] != 0;
    std::vector<int> ts(types);
    std::sort(ts.begin(), ts.end());
    ts.erase(std::unique(ts.begin(), ts.end()), ts.end());
    slots = 0;
    for (int t : ts) {
      std::vector<int> idx;
      for (int g = 0; g < G; ++g)
        if (types[g] == t) idx.push_back(g);
      slots += culled(t, int(idx.size())) ? per_pixel : int(idx.size());
      groups.emplace_back(t, idx);
    }
    any_shadow = false;
    for (int i = 0; i < NL; ++i) any_shadow |= light[i * kLightStride + 21] != 0;
  }

  bool culled(int t, int n) const { return t != 0 && n > std::max(per_pixel, cull_above); }

  // Renderer._choose: the per_pixel geoms of group idx this ray is tested against
  void choose(int t, const std::vector<int>& idx, const T* geo, const T* o, const T* r,
              T reach, T front, int* out, T* score) const {
    int n = int(idx.size());
    for (int j = 0; j < n; ++j) {
      const T* gp = geo + 19 * idx[j];
      const T* c = gp;
      const T* m = gp + 3;
      const T* h = gp + 12;
      T half, rad;
      int col;
      if (t == 2) {
        half = 0, rad = h[0], col = 2;
      } else if (t == 3 || t == 5) {
        half = h[1], rad = h[0], col = 2;
      } else {
        int k = 0;
        if (h[1] > h[k]) k = 1;
        if (h[2] > h[k]) k = 2;
        half = h[k];
        T hh = ((h[0] * h[0] + h[1] * h[1]) + h[2] * h[2]) - half * half;
        rad = std::sqrt(std::max(hh, T(0)));
        col = k;
      }
      T a[3], b[3];
      for (int i = 0; i < 3; ++i) {
        T e = half * m[3 * i + col];
        a[i] = c[i] - e, b[i] = c[i] + e;
      }
      T s_c, dist;
      line_segment(o, r, a, b, s_c, dist);
      T depth = std::max(s_c, near_);
      T lim = rad + reach * depth;
      bool ahead = s_c + half + rad >= front;
      bool core = dist <= rad * T(1.001) + T(1e-6);
      bool band = dist <= lim * T(1.001) + T(1e-6) && ahead;
      score[j] = (core && ahead) ? T(1e6) - s_c
                                 : (band ? -(dist - rad) / depth : T(-1e9) - dist);
    }
    top_k(score, n, per_pixel, out);
  }

  void light_dir(int i, const T* p, T* l, T& dist, T& factor) const {
    const T* L = &light[i * kLightStride];
    int type = int(L[0]);
    if (type == 1) {
      for (int k = 0; k < 3; ++k) l[k] = -L[4 + k];
      dist = T(1e9), factor = 1;
      return;
    }
    T dl[3];
    for (int k = 0; k < 3; ++k) dl[k] = L[1 + k] - p[k];
    dist = std::sqrt(dot3(dl, dl) + T(1e-20));
    for (int k = 0; k < 3; ++k) l[k] = dl[k] / dist;
    factor = T(1) / (L[18] + L[19] * dist + L[20] * dist * dist);
    if (type == 0) {
      T cosang = -dot3(l, L + 4);
      bool inside = cosang >= cutoff_cos[i];
      factor = factor * (inside ? std::exp(L[17] * std::log(std::max(cosang, T(1e-30)))) : T(0));
    }
  }

  // Renderer._unoccluded: 1 if the ray from p to the light meets no geom but `skip`. Every geom
  // is tested (bounding spheres first), where JAX tests a culled type's `per_pixel` nearest: the
  // same verdict wherever those include the occluder.
  T unoccluded(const T* geo, const T* p, const T* l, T dist, int skip) const {
    T o[3];
    for (int k = 0; k < 3; ++k) o[k] = p[k] + T(1e-5) * l[k];
    for (int g = 0; g < G; ++g) {
      int t = types[g];
      if (t == 0 || g == skip) continue;  // a plane casts no shadow upwards
      const T* gp = geo + 19 * g;
      T d[3], ol[3], rl[3];
      for (int k = 0; k < 3; ++k) d[k] = o[k] - gp[k];
      to_local(d, gp + 3, ol);
      to_local(l, gp + 3, rl);
      if (bound_gap(ol, rl, bound_radius(t, gp + 12)) > 0) continue;
      if (hit(t, ol, rl, gp + 12) < dist) return T(0);
    }
    return T(1);
  }

  void shade(const T* p, const T* n, const T* o, const T* fwd, const T* alb, int g,
             const T* lit, T* col) const {
    T v[3];
    for (int k = 0; k < 3; ++k) v[k] = o[k] - p[k];
    T vn = std::sqrt(dot3(v, v) + T(1e-20));
    for (int k = 0; k < 3; ++k) v[k] /= vn;
    T spec_m = spec[g], sh = T(128) * shin[g];
    for (int k = 0; k < 3; ++k) col[k] = emis[g] * alb[k];
    auto add = [&](const T* l, const T* amb, const T* dif, const T* spe, T factor) {
      T ndl = dot3(n, l);
      T h[3] = {l[0] + v[0], l[1] + v[1], l[2] + v[2]};
      T hn = std::sqrt(dot3(h, h) + T(1e-20));
      for (int k = 0; k < 3; ++k) h[k] /= hn;
      T ndh = std::max(dot3(n, h), T(0));
      T sp = ndl > 0 ? std::exp(sh * std::log(ndh + T(1e-30))) : T(0);
      T nd = std::max(ndl, T(0));
      for (int k = 0; k < 3; ++k)
        col[k] = col[k] + amb[k] * alb[k] + factor * (dif[k] * nd * alb[k] + spe[k] * spec_m * sp);
    };
    if (head_on) {
      T l[3] = {-fwd[0], -fwd[1], -fwd[2]};
      add(l, head, head + 3, head + 6, T(1));
    }
    for (int i = 0; i < NL; ++i) {
      const T* L = &light[i * kLightStride];
      T l[3], dist, factor;
      light_dir(i, p, l, dist, factor);
      if (shadows && L[21] != 0) factor = factor * lit[i];
      add(l, L + 7, L + 10, L + 13, factor);
    }
    for (int k = 0; k < 3; ++k) col[k] = std::min(std::max(col[k], T(0)), T(1));
  }
};

// per-thread scratch, one entry per surface slot (a soft image has at most Scene::slots surfaces
// a pixel, a hard one every geom)
template <typename T>
struct Scratch {
  // per surface: first hit, depth where it is placed, coverage, depth then distance, world
  // point, point in the geom's frame (for its normal, found only where it is shaded), albedo
  std::vector<T> s_hit, s_n, cover, z, p, pl, alb, score;
  std::vector<int> gid, type, pick, lay;
  std::vector<T> lit, ahead;
  std::vector<T> ol, oo, rb;  // per geom, per frame
  int64_t frame = -1;
  Scratch(int slots, int G, int NL) : lit(std::max(NL, 1)), ol(3 * G), oo(G), rb(G) {
    const size_t S = std::max(slots, G);
    for (auto* v : {&s_hit, &s_n, &cover, &z, &score}) v->resize(S);
    for (auto* v : {&p, &pl}) v->resize(3 * S);
    alb.resize(4 * S);
    ahead.resize(S * S);
    for (auto* v : {&gid, &type, &pick, &lay}) v->resize(S);
  }
};

// ahead[g * S + k]: how much surface k lies in front of surface g (soft: a sigmoid of their depth
// difference over gamma; hard: 0 or 1); only between two surfaces that both cover the pixel,
// the only pairs `composite` reads
template <typename T>
void depth_order(int S, const T* a, const T* z, bool soft, T gamma, T* ahead) {
  for (int g = 0; g < S; ++g)
    for (int k = g + 1; k < S; ++k) {
      if (a[g] == 0 || a[k] == 0) continue;
      if (soft) {
        T e = std::exp((z[k] - z[g]) / gamma);  // sigmoid((z_g - z_k) / gamma) = 1 / (1 + e)
        ahead[g * S + k] = T(1) / (T(1) + e);
        ahead[k * S + g] = T(1) / (T(1) + T(1) / e);
      } else {
        ahead[g * S + k] = T(z[k] < z[g] ? 1 : 0);
        ahead[k * S + g] = T(z[g] < z[k] ? 1 : 0);
      }
    }
}

// w_g = a_g prod_{k != g} (1 - a_k ahead[g, k]), background prod_k (1 - a_k), both normalised
template <typename T>
void composite(int S, const T* a, const T* ahead, T* w, T& bg) {
  T tot = 0;
  bg = 1;
  for (int k = 0; k < S; ++k) bg = k == 0 ? T(1) - a[0] : bg * (T(1) - a[k]);
  for (int g = 0; g < S; ++g) {
    T prod = 1;
    for (int k = 0; k < S; ++k) {
      T occl = 1;
      if (k != g && a[k] != 0 && a[g] != 0) occl = T(1) - a[k] * ahead[g * S + k];
      prod = k == 0 ? occl : prod * occl;
    }
    w[g] = a[g] * prod;
    tot = g == 0 ? w[0] : tot + w[g];
  }
  tot = tot + bg;
  tot = tot > 0 ? tot : T(1);
  for (int g = 0; g < S; ++g) w[g] = w[g] / tot;
  bg = bg / tot;
}

template <typename T>
void draw_pixel(const Scene<T>& sc, const T* cam, const T* geo, int i, int j, Scratch<T>& X, T* rgb, T* depth, int32_t* seg, int32_t* body, T* weights,
                T* background) {
  // X.ol / X.oo / X.rb: the camera in each geom's frame, its squared distance from the geom's
  // centre and the geom's bounding radius (per frame: set by the caller)
  const int G = sc.G;
  const bool soft = sc.tau != 0;
  const T* o = cam;
  const T* cm = cam + 3;
  T px = cam[12], cx = cam[13], cy = cam[14];
  T loc[3] = {(T(j) + T(0.5) - cx) * px, (cy - T(i) - T(0.5)) * px, T(-1)};
  T r[3];
  for (int k = 0; k < 3; ++k) r[k] = (loc[0] * cm[3 * k] + loc[1] * cm[3 * k + 1]) + loc[2] * cm[3 * k + 2];
  T fwd[3] = {-cm[2], -cm[5], -cm[8]};
  T band = soft ? T(15) * sc.tau + T(2) : T(2);
  T reach = band * px, ntau = sc.tau * px;

  int S = 0;
  for (const auto& grp : sc.groups) {
    int t = grp.first;
    const auto& idx = grp.second;
    int n = int(idx.size());
    // Culling only ever drops coverage from the soft image: the hard image tests every geom
    // (bounding spheres first), which is what culling keeps it equal to.
    bool cull = soft && sc.culled(t, n);
    if (cull) sc.choose(t, idx, geo, o, r, reach, sc.near_, X.pick.data(), X.score.data());
    int m = cull ? sc.per_pixel : n;
    for (int q = 0; q < m; ++q, ++S) {
      int g = idx[cull ? X.pick[q] : q];
      const T* gp = geo + 19 * g;
      const T* xm = gp + 3;
      const T* sz = gp + 12;
      const T* ol = &X.ol[3 * g];
      T rl[3];
      to_local(r, xm, rl);
      T rb = X.rb[g];
      T gap = -1;
      if (t != 0) {  // does the ray miss the bounding sphere? (squared, no root)
        T rr = dot3(rl, rl), orr = dot3(ol, rl), rbm = rb * T(1.001) + T(1e-6);
        T miss = X.oo[g] * rr - orr * orr - rbm * rbm * rr;
        if (miss > 0) gap = soft ? bound_gap(ol, rl, rb) : T(1);
      }
      T s_hit = gap > 0 ? K<T>::inf() : hit(t, ol, rl, sz);
      T sn, dist = 0;
      if (!soft) {
        sn = s_hit;
      } else if (far_from(t, ol, rl, rb, gap, px, sc.near_, T(30) * sc.tau)) {
        // the ray passes so far from the geom's bounding sphere that its coverage is under
        // sigmoid(-30) ~ 1e-13: nothing to search for; it adds nothing to the pixel
        sn = -dot3(ol, rl) / dot3(rl, rl);
        sn = std::isfinite(sn) ? sn : sc.far_;
        dist = K<T>::inf();
      } else {
        T s_c;
        closest(t, ol, rl, sz, sc.iters, s_c, dist);
        sn = std::isfinite(s_hit) ? s_hit : s_c;
        sn = std::isfinite(sn) ? sn : sc.far_;
      }
      // the normal is found only where the surface is shaded (draw_pixel's shading loop)
      T sp = soft ? sn : (std::isfinite(s_hit) ? s_hit : sc.far_);
      for (int k = 0; k < 3; ++k) X.pl[3 * S + k] = ol[k] + sp * rl[k];
      X.s_hit[S] = (s_hit >= sc.near_ && s_hit <= sc.far_) ? s_hit : K<T>::inf();
      X.s_n[S] = sn;
      X.z[S] = dist;  // soft: the signed distance, turned into coverage below
      for (int k = 0; k < 4; ++k) X.alb[4 * S + k] = gp[15 + k];
      X.gid[S] = g;
      X.type[S] = t;
    }
  }
  // first hit: segmentation, body, hard depth
  int first = 0;
  bool any_hit = false;
  for (int k = 0; k < S; ++k) {
    if (X.s_hit[k] < X.s_hit[first]) first = k;
    any_hit |= std::isfinite(X.s_hit[k]);
  }
  *seg = any_hit ? sc.gids[X.gid[first]] : -1;
  *body = any_hit ? sc.bodies[X.gid[first]] : -1;
  for (int k = 0; k < S; ++k) {
    bool h = std::isfinite(X.s_hit[k]);
    T zk;
    if (!soft) {
      zk = h ? X.s_hit[k] : sc.far_;
      X.cover[k] = h ? T(1) : T(0);
    } else {
      zk = X.s_n[k];
      T d_px = X.z[k] / (std::max(zk, sc.near_) * px);
      X.cover[k] = sigmoid(-d_px / sc.tau) * T(zk >= sc.near_ && zk <= sc.far_ ? 1 : 0);
    }
    X.z[k] = zk;
    for (int q = 0; q < 3; ++q) X.p[3 * k + q] = o[q] + zk * r[q];
  }
  // the `layers` most covering surfaces not hidden behind a solid one
  int L = S;
  int* lay = X.lay.data();
  for (int k = 0; k < S; ++k) lay[k] = k;
  if (S > sc.layers) {
    T solid = K<T>::inf();
    for (int k = 0; k < S; ++k)
      if (X.cover[k] > T(0.999)) solid = std::min(solid, X.z[k]);
    T* key = X.score.data();
    for (int k = 0; k < S; ++k) {
      bool shown = X.z[k] <= solid + (soft ? T(10) * sc.gamma : T(0));
      key[k] = shown ? X.cover[k] - T(1e-6) * X.z[k] / sc.far_ : T(-1) - X.z[k] / sc.far_;
    }
    top_k(key, S, sc.layers, lay);
    L = sc.layers;
  }
  T a[64], zz[64], w[64], wa[64];
  for (int k = 0; k < L; ++k) a[k] = X.cover[lay[k]], zz[k] = X.z[lay[k]];
  T bg, bg_rgb;
  T* ahead = X.ahead.data();
  depth_order(L, a, zz, soft, sc.gamma, ahead);
  composite(L, a, ahead, w, bg);
  T* lit = X.lit.data();
  if (sc.shadows && sc.any_shadow) {
    int win = 0;
    for (int k = 1; k < L; ++k)
      if (w[k] > w[win]) win = k;
    const T* pw = &X.p[3 * lay[win]];
    int gw = X.gid[lay[win]];
    for (int li = 0; li < sc.NL; ++li) {
      if (sc.light[li * kLightStride + 21] == 0) continue;
      T l[3], dist, factor;
      sc.light_dir(li, pw, l, dist, factor);
      lit[li] = sc.unoccluded(geo, pw, l, dist, gw);
    }
  }
  T out[3] = {0, 0, 0};
  for (int k = 0; k < L; ++k) wa[k] = a[k] * X.alb[4 * lay[k] + 3];
  T wrgb[64];
  composite(L, wa, ahead, wrgb, bg_rgb);
  for (int k = 0; k < L; ++k) {
    // a surface that adds nothing here is not shaded: the hard image's hidden ones (weight
    // exactly 0), the soft one's far from their silhouette (coverage under 1e-12)
    if (!(wrgb[k] > T(1e-12))) continue;
    int s = lay[k];
    const T* gp = geo + 19 * X.gid[s];
    T nl[3], nw[3];
    normal(X.type[s], &X.pl[3 * s], gp + 12, soft, ntau * X.s_n[s], nl);
    to_world(nl, gp + 3, nw);
    T nn = std::sqrt(dot3(nw, nw) + T(1e-20));
    for (int q = 0; q < 3; ++q) nw[q] /= nn;
    T col[3];
    sc.shade(&X.p[3 * s], nw, o, fwd, &X.alb[4 * s], X.gid[s], lit, col);
    for (int q = 0; q < 3; ++q) out[q] = out[q] + wrgb[k] * col[q];
  }
  for (int q = 0; q < 3; ++q) rgb[q] = out[q];
  if (soft) {
    T dsum = 0;
    for (int k = 0; k < L; ++k) dsum = k == 0 ? w[0] * zz[0] : dsum + w[k] * zz[k];
    *depth = dsum + bg * sc.far_depth;
  } else {
    *depth = any_hit ? X.s_hit[first] : sc.far_depth;
  }
  for (int g = 0; g < G; ++g) weights[g] = 0;
  for (int k = 0; k < L; ++k) weights[X.gid[lay[k]]] += w[k];
  *background = bg;
}

int worker_count(int64_t rows) {
  int n = 1;
#if defined(__linux__)
  cpu_set_t set;
  if (sched_getaffinity(0, sizeof(set), &set) == 0) n = CPU_COUNT(&set);
#else
  n = int(std::thread::hardware_concurrency());
#endif
  if (const char* env = std::getenv("TWINRL_RENDER_THREADS")) n = std::max(1, std::atoi(env));
  return int(std::max<int64_t>(1, std::min<int64_t>(n, rows)));
}

template <typename T, ffi::DataType DT>
ffi::Error Render(ffi::Buffer<DT> cam, ffi::Buffer<DT> geo, ffi::ResultBuffer<DT> rgb,
                  ffi::ResultBuffer<DT> depth, ffi::ResultBuffer<ffi::S32> seg,
                  ffi::ResultBuffer<ffi::S32> body, ffi::ResultBuffer<DT> weights,
                  ffi::ResultBuffer<DT> background, Config cfg) {
  Scene<T> sc(cfg);
  auto dims = rgb->dimensions();
  if (dims.size() < 3) return ffi::Error::InvalidArgument("rgb must be (..., H, W, 3)");
  const int64_t H = dims[dims.size() - 3], W = dims[dims.size() - 2];
  const int64_t N = int64_t(rgb->element_count()) / (H * W * 3);
  const int G = sc.G;
  if (int64_t(cam.element_count()) != N * 15 || int64_t(geo.element_count()) != N * G * 19)
    return ffi::Error::InvalidArgument("camera or geom batch does not match the image batch");
  if (sc.slots > 64 || G > 64)
    return ffi::Error::InvalidArgument("more than 64 geoms or surfaces a pixel");
  const T* camp = cam.typed_data();
  const T* geop = geo.typed_data();
  T* rgbp = rgb->typed_data();
  T* depp = depth->typed_data();
  int32_t* segp = seg->typed_data();
  int32_t* bodp = body->typed_data();
  T* wp = weights->typed_data();
  T* bgp = background->typed_data();
  const int64_t rows = N * H;
  auto run = [&](int64_t r0, int64_t r1) {
    Scratch<T> X(sc.slots, G, sc.NL);
    for (int64_t row = r0; row < r1; ++row) {
      int64_t b = row / H, i = row % H;
      const T* c = camp + 15 * b;
      const T* g = geop + int64_t(19) * G * b;
      if (X.frame != b) {  // the camera in each geom's frame
        for (int k = 0; k < G; ++k) {
          const T* gp = g + 19 * k;
          T d[3] = {c[0] - gp[0], c[1] - gp[1], c[2] - gp[2]};
          to_local(d, gp + 3, &X.ol[3 * k]);
          X.oo[k] = dot3(&X.ol[3 * k], &X.ol[3 * k]);
          X.rb[k] = bound_radius(sc.types[k], gp + 12);
        }
        X.frame = b;
      }
      for (int64_t j = 0; j < W; ++j) {
        int64_t px = (b * H + i) * W + j;
        draw_pixel(sc, c, g, int(i), int(j), X, rgbp + 3 * px, depp + px,
                   segp + px, bodp + px, wp + int64_t(G) * px, bgp + px);
      }
    }
  };
  int nw = worker_count(rows);
  if (nw == 1) {
    run(0, rows);
  } else {
    std::vector<std::thread> pool;
    for (int k = 1; k < nw; ++k)
      pool.emplace_back(run, rows * k / nw, rows * (k + 1) / nw);
    run(0, rows / nw);
    for (auto& t : pool) t.join();
  }
  return ffi::Error::Success();
}

}  // namespace

#define TWINRL_BIND(DT)                                   \
  ffi::Ffi::Bind()                                        \
      .Arg<ffi::Buffer<DT>>()                             \
      .Arg<ffi::Buffer<DT>>()                             \
      .Ret<ffi::Buffer<DT>>()                             \
      .Ret<ffi::Buffer<DT>>()                             \
      .Ret<ffi::Buffer<ffi::S32>>()                       \
      .Ret<ffi::Buffer<ffi::S32>>()                       \
      .Ret<ffi::Buffer<DT>>()                             \
      .Ret<ffi::Buffer<DT>>()                             \
      .Attr<ffi::Span<const int32_t>>("types")            \
      .Attr<ffi::Span<const int32_t>>("gids")             \
      .Attr<ffi::Span<const int32_t>>("bodies")           \
      .Attr<ffi::Span<const int32_t>>("opts")             \
      .Attr<ffi::Span<const double>>("mat")               \
      .Attr<ffi::Span<const double>>("lights")            \
      .Attr<ffi::Span<const double>>("headlight")         \
      .Attr<ffi::Span<const double>>("scal")

template <typename T, ffi::DataType DT>
static ffi::Error RenderEntry(ffi::Buffer<DT> cam, ffi::Buffer<DT> geo,
                              ffi::ResultBuffer<DT> rgb, ffi::ResultBuffer<DT> depth,
                              ffi::ResultBuffer<ffi::S32> seg, ffi::ResultBuffer<ffi::S32> body,
                              ffi::ResultBuffer<DT> weights, ffi::ResultBuffer<DT> background,
                              ffi::Span<const int32_t> types, ffi::Span<const int32_t> gids,
                              ffi::Span<const int32_t> bodies, ffi::Span<const int32_t> opts,
                              ffi::Span<const double> mat, ffi::Span<const double> lights,
                              ffi::Span<const double> headlight, ffi::Span<const double> scal) {
  Config cfg{types, gids, bodies, opts, mat, lights, headlight, scal};
  return Render<T, DT>(cam, geo, rgb, depth, seg, body, weights, background, cfg);
}

XLA_FFI_DEFINE_HANDLER_SYMBOL(TwinrlRenderF32, (RenderEntry<float, ffi::F32>), TWINRL_BIND(ffi::F32));
XLA_FFI_DEFINE_HANDLER_SYMBOL(TwinrlRenderF64, (RenderEntry<double, ffi::F64>), TWINRL_BIND(ffi::F64));
