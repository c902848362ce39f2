// The renderer's image and its reverse pass, as XLA FFI custom calls on the CPU.
//
// The same arithmetic as twinrl/render/renderer.py's Renderer._render and primitives.py (read
// those for the why of each step): rays from a pinhole camera, each drawn primitive's first hit
// and (soft image) closest approach and normal in its local frame, per-pixel culling of crowded
// types, the `layers` most covering surfaces, front-to-back compositing with a smooth depth
// order, hard shadow rays and OpenGL's fixed-function shading. XLA runs the JAX version as
// hundreds of passes over (pixel, surface) arrays; here each pixel is drawn start to finish in
// registers, the frames' rows split across the CPU's cores. The reverse pass (RenderVjp) draws
// each pixel again and differentiates it backwards: by hand through the composite and the
// shading, and through each surface's geometry on forward-mode Dual numbers (the same
// templates, with JAX's own derivative rules where primitives.py defines them: a search's
// result held constant, a cylinder's kinks). Forward mode stays with the JAX version
// (renderer.py's custom JVP). Meshes are not drawn here (the Python side falls back to JAX).
//
// What it skips leaves the image as JAX draws it: a ray that misses a geom's bounding sphere is
// not intersected with it; a surface is shaded only where it adds to the pixel (weight > 1e-12);
// a soft silhouette 30 tau pixels away (coverage < 1e-13) is not searched for. The hard image
// and shadow rays test every geom, where JAX culls crowded types to the nearest few (exact
// wherever those hold the first hit, resp. the occluder; culling only ever drops soft coverage).
//
// The reverse pass leaves out, besides, what adds under 1e-10 to a pixel: a surface whose
// coverage is under that, a distance where the coverage's sigmoid is that flat.
//
// Inputs: cam (..., 15) = pos (3), xmat (9, row-major; columns right, up, back), pixel size at
// unit depth, principal column and row; geo (..., G, 19) = xpos (3), xmat (9), size (3), albedo
// rgba (4), the renderer's geoms in its order; tg (..., 2) = the soft silhouette's temperature
// tau in pixels (0: the hard image) and the depth order's gamma. Outputs: rgb (..., H, W, 3), depth (..., H, W),
// segmentation and body ids (..., H, W) int32, weights (..., H, W, G), background (..., H, W).
// The reverse pass takes cam, geo, tg and the cotangents of rgb, depth, weights and background, and
// gives those of cam and geo.

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
  static T eps() { return T(1e-12); }
  static T inf() { return T(std::numeric_limits<double>::infinity()); }
};

// ------------------------------------------------------------------ forward-mode numbers
// Dual<T, N>: a value and its derivatives along N directions. The reverse kernel (draw_pixel_vjp)
// runs each surface's geometry (hit, closest approach, normal: the same templates the image
// uses) on these, seeded with the surface's 10 inputs, to get their Jacobian; the rest of a
// pixel (compositing, shading) is differentiated by hand. Ties of min / max / |x| split as JAX's
// derivatives do (half each; |x|' = 0 at 0), so that both give the same gradient.
template <typename T, int N>
struct Dual {
  T v;
  T d[N];
  Dual() = default;
  Dual(double x) : v(T(x)) {  // NOLINT: constants mix freely
    for (int k = 0; k < N; ++k) d[k] = T(0);
  }
  static Dual seed(T x, int k) {
    Dual r(0.0);
    r.v = x;
    r.d[k] = T(1);
    return r;
  }
  friend Dual operator+(const Dual& a, const Dual& b) {
    Dual r;
    r.v = a.v + b.v;
    for (int k = 0; k < N; ++k) r.d[k] = a.d[k] + b.d[k];
    return r;
  }
  friend Dual operator-(const Dual& a, const Dual& b) {
    Dual r;
    r.v = a.v - b.v;
    for (int k = 0; k < N; ++k) r.d[k] = a.d[k] - b.d[k];
    return r;
  }
  friend Dual operator-(const Dual& a) {
    Dual r;
    r.v = -a.v;
    for (int k = 0; k < N; ++k) r.d[k] = -a.d[k];
    return r;
  }
  friend Dual operator*(const Dual& a, const Dual& b) {
    Dual r;
    r.v = a.v * b.v;
    for (int k = 0; k < N; ++k) r.d[k] = a.d[k] * b.v + a.v * b.d[k];
    return r;
  }
  friend Dual operator/(const Dual& a, const Dual& b) {
    Dual r;
    r.v = a.v / b.v;
    T ib = T(1) / b.v;
    for (int k = 0; k < N; ++k) r.d[k] = (a.d[k] - r.v * b.d[k]) * ib;
    return r;
  }
  Dual& operator+=(const Dual& b) { return *this = *this + b; }
  Dual& operator-=(const Dual& b) { return *this = *this - b; }
  Dual& operator*=(const Dual& b) { return *this = *this * b; }
  Dual& operator/=(const Dual& b) { return *this = *this / b; }
  friend bool operator<(const Dual& a, const Dual& b) { return a.v < b.v; }
  friend bool operator>(const Dual& a, const Dual& b) { return a.v > b.v; }
  friend bool operator<=(const Dual& a, const Dual& b) { return a.v <= b.v; }
  friend bool operator>=(const Dual& a, const Dual& b) { return a.v >= b.v; }
  friend bool operator==(const Dual& a, const Dual& b) { return a.v == b.v; }
  friend bool operator!=(const Dual& a, const Dual& b) { return a.v != b.v; }
};

template <typename T> struct IsDual { static constexpr bool value = false; };
template <typename T, int N> struct IsDual<Dual<T, N>> { static constexpr bool value = true; };

// a Dual's value (a plain number as it is) and the same number held constant (stop_gradient)
template <typename T> inline T value(T x) { return x; }
template <typename T, int N> inline T value(const Dual<T, N>& x) { return x.v; }
template <typename T> inline T constant(T x) { return x; }
template <typename T, int N> inline Dual<T, N> constant(const Dual<T, N>& x) {
  Dual<T, N> r(0.0);
  r.v = x.v;
  return r;
}
template <typename T> struct Base { using type = T; };
template <typename T, int N> struct Base<Dual<T, N>> { using type = T; };

// f(x) with derivative f'(x) (the chain rule once, for the unary functions below)
template <typename T, int N>
inline Dual<T, N> chain(const Dual<T, N>& x, T f, T df) {
  Dual<T, N> r;
  r.v = f;
  for (int k = 0; k < N; ++k) r.d[k] = df * x.d[k];
  return r;
}

template <typename T> inline T Sqrt(T x) { return std::sqrt(x); }
template <typename T> inline T Exp(T x) { return std::exp(x); }
template <typename T> inline T Log(T x) { return std::log(x); }
template <typename T> inline T Fabs(T x) { return std::fabs(x); }
template <typename T> inline bool Finite(T x) { return std::isfinite(x); }
template <typename T> inline T Min(const T& a, const T& b) { return b < a ? b : a; }
template <typename T> inline T Max(const T& a, const T& b) { return a < b ? b : a; }

template <typename T, int N> inline Dual<T, N> Sqrt(const Dual<T, N>& x) {
  T s = std::sqrt(x.v);
  return chain(x, s, T(0.5) / s);
}
template <typename T, int N> inline Dual<T, N> Exp(const Dual<T, N>& x) {
  T e = std::exp(x.v);
  return chain(x, e, e);
}
template <typename T, int N> inline Dual<T, N> Log(const Dual<T, N>& x) {
  return chain(x, T(std::log(x.v)), T(1) / x.v);
}
template <typename T, int N> inline Dual<T, N> Fabs(const Dual<T, N>& x) {
  return chain(x, T(std::fabs(x.v)), T(x.v > 0 ? 1 : (x.v < 0 ? -1 : 0)));
}
template <typename T, int N> inline bool Finite(const Dual<T, N>& x) { return std::isfinite(x.v); }
template <typename T, int N>
inline Dual<T, N> Min(const Dual<T, N>& a, const Dual<T, N>& b) {
  if (a.v == b.v) return (a + b) * Dual<T, N>(0.5);
  return b.v < a.v ? b : a;
}
template <typename T, int N>
inline Dual<T, N> Max(const Dual<T, N>& a, const Dual<T, N>& b) {
  if (a.v == b.v) return (a + b) * Dual<T, N>(0.5);
  return a.v < b.v ? b : a;
}

template <typename T>
inline T dot3(const T* a, const T* b) { return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]; }

template <typename T>
inline T safe_div(T a, T b) {
  T e = K<T>::eps();
  return a / (Fabs(b) > e ? b : (b < 0 ? -e : e));
}

template <typename T>
inline T first_positive(T c) { return c > 0 ? c : K<T>::inf(); }

template <typename T>
inline T sigmoid(T x) { return T(1) / (T(1) + Exp(-x)); }

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
  A = A > K<T>::eps() ? A : K<T>::eps();
  T f = B / A, ll = 0;
  for (int k = 0; k < n; ++k) {
    T lc = o[k] - f * r[k];
    ll = k == 0 ? lc * lc : ll + lc * lc;
  }
  T disc = A * (rad * rad - ll);
  T sq = disc > 0 ? Sqrt(disc) : T(0);
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
  bool good = ok && Fabs(z) <= h && (r[0] * r[0] + r[1] * r[1]) > K<T>::eps();
  return good ? first_positive(s0) : K<T>::inf();
}

template <typename T>
T hit(int type, const T* o, const T* r, const T* sz) {
  const T inf = K<T>::inf();
  switch (type) {
    case 0: {  // plane z = 0, front side, finite rectangle where sizes > 0
      T s = safe_div(-o[2], r[2]);
      T px = o[0] + s * r[0], py = o[1] + s * r[1];
      bool in = (sz[0] > 0 ? Fabs(px) <= sz[0] : true) &&
                (sz[1] > 0 ? Fabs(py) <= sz[1] : true);
      return (o[2] > 0 && r[2] < 0 && in && s > 0) ? s : inf;
    }
    case 2:
      return hit_sphere(o, r, sz[0]);
    case 3: {
      T rad = sz[0], h = sz[1];
      T side = hit_tube(o, r, rad, h);
      T ot[3] = {o[0], o[1], o[2] - h}, ob[3] = {o[0], o[1], o[2] + h};
      return Min(side, Min(hit_sphere(ot, r, rad), hit_sphere(ob, r, rad)));
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
        caps = Min(caps, in ? first_positive(s) : inf);
      }
      return Min(side, caps);
    }
    case 6: {
      T tmin = 0, tmax = 0;
      for (int k = 0; k < 3; ++k) {
        T t1 = safe_div(-sz[k] - o[k], r[k]), t2 = safe_div(sz[k] - o[k], r[k]);
        T lo = Min(t1, t2), hi = Max(t1, t2);
        tmin = k == 0 ? lo : Max(tmin, lo);
        tmax = k == 0 ? hi : Min(tmax, hi);
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
  T z = -dot3(u, v) / Max(vv, K<T>::eps());
  z = Min(Max(z, T(0)), T(1));
  T p[3];
  for (int k = 0; k < 3; ++k) p[k] = u[k] + z * v[k];
  s = s0 + ds * z;
  d = Sqrt(dot3(p, p) + T(1e-20));
}

template <typename T>
inline T sdf_cylinder(const T* p, T rad, T h) {
  T rxy = Sqrt(p[0] * p[0] + p[1] * p[1] + T(1e-20));
  T q0 = rxy - rad, q1 = Fabs(p[2]) - h;
  T a = Max(q0, T(0)), b = Max(q1, T(0));
  return Min(Max(q0, q1), T(0)) + Sqrt(a * a + b * b + T(1e-20));
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

template <typename D>
void closest_cylinder_dual(const D* o, const D* r, const D* sz, int iters, D& s, D& d);

template <typename T>
void closest(int type, const T* o, const T* r, const T* sz, int iters, T& s, T& d) {
  const T inf = K<T>::inf();
  switch (type) {
    case 0: {
      T sp = safe_div(-o[2], r[2]);
      T px = o[0] + sp * r[0], py = o[1] + sp * r[1];
      bool front = o[2] > 0 && r[2] < 0;
      T qx = Fabs(px) - sz[0], qy = Fabs(py) - sz[1];
      bool finite = sz[0] > 0 && sz[1] > 0;
      T a = Max(qx, T(0)), b = Max(qy, T(0));
      T dd = Min(Max(qx, qy), T(0)) + Sqrt(a * a + b * b + T(1e-20));
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
      d = Sqrt(dot3(p, p) + T(1e-20)) - sz[0];
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
      if constexpr (IsDual<T>::value) {  // the derivatives JAX's closest_cylinder defines
        closest_cylinder_dual(o, r, sz, iters, s, d);
        return;
      }
      T rad = sz[0], h = sz[1];
      T rb = Sqrt(rad * rad + h * h);
      T rr = dot3(r, r);
      T sc = -dot3(o, r) / rr;
      T half = rb / Sqrt(rr) * T(1.05) + T(1e-6);
      T lo = Max(sc - half, T(1e-6)), hi = Max(sc + half, T(2e-6));
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
      // inside: the deepest point (box_depth); outside: the nearest edge. The searches run on
      // values (V; on Dual numbers only the chosen piece is differentiated, as in JAX)
      using V = typename Base<T>::type;
      T A[3], P[3], Q[3];
      V Av[3], Pv[3], Qv[3], ov[3], rv[3], hv[3];
      for (int k = 0; k < 3; ++k) {
        T sg = r[k] >= 0 ? T(1) : T(-1);
        A[k] = sg * r[k];
        P[k] = sg * o[k] - sz[k];
        Q[k] = -sg * o[k] - sz[k];
        Av[k] = value(A[k]), Pv[k] = value(P[k]), Qv[k] = value(Q[k]);
        ov[k] = value(o[k]), rv[k] = value(r[k]), hv[k] = value(sz[k]);
      }
      const V vinf = std::numeric_limits<V>::infinity();
      V best_v = 0, best_s = 0;
      int bi = 0, bj = 0;
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
          V den = Av[i] + Av[j];
          bool ok = den > 0;
          den = ok ? den : V(1);
          V v = ok ? (Av[i] * Qv[j] + Av[j] * Pv[i]) / den : -vinf;
          V sv = (Qv[j] - Pv[i]) / den;
          if (i == 0 && j == 0) {
            best_v = v, best_s = sv;
          } else if (v > best_v) {
            best_v = v, best_s = sv, bi = i, bj = j;
          }
        }
      T d_in = (A[bi] * Q[bj] + A[bj] * P[bi]) / (A[bi] + A[bj]);
      if (d_in < 0) {
        s = T(best_s), d = d_in;  // s held constant, as JAX's box_depth
        return;
      }
      V rr = dot3(rv, rv), irr = V(1) / rr;
      int best_k = 0;
      V best_d = vinf;
      for (int k = 0; k < 12; ++k) {
        V a[3], e[3];
        for (int i = 0; i < 3; ++i) a[i] = V(kBox.a[k][i]) * hv[i], e[i] = V(kBox.e[k][i]) * hv[i];
        V s0 = ((a[0] - ov[0]) * rv[0] + (a[1] - ov[1]) * rv[1] + (a[2] - ov[2]) * rv[2]) * irr;
        V ds = (e[0] * rv[0] + e[1] * rv[1] + e[2] * rv[2]) * irr;
        V u[3], v[3];
        for (int i = 0; i < 3; ++i) u[i] = ov[i] + s0 * rv[i] - a[i], v[i] = ds * rv[i] - e[i];
        V vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
        V uv = u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
        V z = Min(Max(-uv / Max(vv, K<V>::eps()), V(0)), V(1));
        V x0 = u[0] + z * v[0], x1 = u[1] + z * v[1], x2 = u[2] + z * v[2];
        V dd = x0 * x0 + x1 * x1 + x2 * x2;
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

// d/du sdf_cylinder(o + u r) at u = t: its derivative along the ray, as JAX's jvp of it (ties of
// max / min / |x| half and half)
template <typename U>
U cylinder_slope(U t, const U* o, const U* r, const U* sz) {
  using T = typename Base<U>::type;
  auto pick = [](T a, T b, U da, U db) {  // d max(a, b)
    return a > b ? da : (b > a ? db : (da + db) * U(0.5));
  };
  U p[3] = {o[0] + t * r[0], o[1] + t * r[1], o[2] + t * r[2]};
  U rxy = Sqrt(p[0] * p[0] + p[1] * p[1] + U(1e-20));
  U q0 = rxy - sz[0], q1 = Fabs(p[2]) - sz[1];
  U dq0 = (p[0] * r[0] + p[1] * r[1]) / rxy;
  T pz = value(p[2]);
  U dq1 = (pz > 0 ? r[2] : (pz < 0 ? -r[2] : U(0)));
  T q0v = value(q0), q1v = value(q1), m = std::max(q0v, q1v);
  U dm = pick(q0v, q1v, dq0, dq1);
  U dmn = m < 0 ? dm : (m > 0 ? U(0) : dm * U(0.5));
  U a = Max(q0, U(0)), b = Max(q1, U(0));
  U da = pick(q0v, T(0), dq0, U(0)), db = pick(q1v, T(0), dq1, U(0));
  U sq = Sqrt(a * a + b * b + U(1e-20));
  return dmn + (a * da + b * db) / sq;
}

// closest(5, ...) on Dual numbers: the values of the search, and the derivatives JAX's
// primitives.closest_cylinder gives them: the search's s held constant, except outside, where
// it moves by the implicit function theorem; inside, on a kink of the SDF, Danskin's mix of the
// two pieces (read closest_cylinder for why)
template <typename D>
void closest_cylinder_dual(const D* o, const D* r, const D* sz, int iters, D& s_out, D& d_out) {
  using T = typename Base<D>::type;
  T ov[3], rv[3], hv[3];
  for (int k = 0; k < 3; ++k) ov[k] = value(o[k]), rv[k] = value(r[k]), hv[k] = value(sz[k]);
  T sv, dv;
  closest<T>(5, ov, rv, hv, iters, sv, dv);
  T rb = std::sqrt(hv[0] * hv[0] + hv[1] * hv[1]);
  T rr = dot3(rv, rv);
  T sc = -dot3(ov, rv) / rr;
  T half = rb / std::sqrt(rr) * T(1.05) + T(1e-6);
  T lo = std::max(sc - half, T(1e-6)), hi = std::max(sc + half, T(2e-6));
  T width = (hi - lo) * T(std::pow(0.6180339887498949, iters));
  D S = D(0.0);
  S.v = sv;
  D p[3];
  for (int k = 0; k < 3; ++k) p[k] = o[k] + S * r[k];
  T ps[3] = {value(p[0]), value(p[1]), value(p[2])};
  bool z_kink = std::fabs(ps[2]) <= std::fabs(rv[2]) * width;
  D rxy = Sqrt(p[0] * p[0] + p[1] * p[1] + D(1e-20));
  D q0 = rxy - sz[0];
  D q1 = (z_kink ? constant(Fabs(p[2])) : Fabs(p[2])) - sz[1];
  T d0 = (ps[0] * rv[0] + ps[1] * rv[1]) / value(rxy);
  T d1 = z_kink ? T(0) : (ps[2] > 0 ? rv[2] : (ps[2] < 0 ? -rv[2] : T(0)));
  T q0s = value(q0), q1s = value(q1);
  bool inside = std::max(q0s, q1s) < 0;
  bool kink = d0 * d1 < 0 && std::fabs(q0s - q1s) <= (std::fabs(d0) + std::fabs(d1)) * width;
  T lam = safe_div(d1, d1 - d0);
  D g = kink ? D(lam) * q0 + D(T(1) - lam) * q1 : (q1s > q0s ? q1 : q0);
  D dd = sdf_cylinder(p, sz[0], sz[1]);
  // f'' along the ray at s (a constant): the slope's own derivative in s
  using D1 = Dual<T, 1>;
  D1 o1[3], r1[3], h1[3];
  for (int k = 0; k < 3; ++k) o1[k] = D1(0.0), r1[k] = D1(0.0), h1[k] = D1(0.0);
  for (int k = 0; k < 3; ++k) o1[k].v = ov[k], r1[k].v = rv[k], h1[k].v = hv[k];
  T curve = cylinder_slope(D1::seed(sv, 0), o1, r1, h1).d[0];
  bool curved = curve > K<T>::eps();
  D step = -cylinder_slope(S, o, r, sz) / D(curved ? curve : T(1));
  s_out = (!inside && curved) ? S + step - constant(step) : S;
  d_out = inside ? constant(dd) + g - constant(g) : dd;
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
      T z = Min(Max(p[2], -sz[1]), sz[1]);
      n[0] = p[0], n[1] = p[1], n[2] = p[2] - z;
      return;
    }
    case 4:
      for (int k = 0; k < 3; ++k) n[k] = p[k] / (sz[k] * sz[k]);
      return;
    case 5: {
      T rxy = Sqrt(p[0] * p[0] + p[1] * p[1] + T(1e-20));
      T dr = Fabs(rxy - sz[0]), dz = Fabs(Fabs(p[2]) - sz[1]);
      T w_cap = soft ? sigmoid((dr - dz) / tn) : T(dz < dr ? 1 : 0);
      T side = (T(1) - w_cap) / rxy;
      n[0] = side * p[0], n[1] = side * p[1], n[2] = w_cap * (p[2] >= 0 ? T(1) : T(-1));
      return;
    }
    case 6: {
      T d[3], w[3];
      for (int k = 0; k < 3; ++k) d[k] = Fabs(Fabs(p[k]) - sz[k]);
      if (soft) {
        T lo = Min(Min(d[0], d[1]), d[2]);
        T e[3];
        for (int k = 0; k < 3; ++k) e[k] = Exp((lo - d[k]) / tn);
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
    case 4: return Max(Max(sz[0], sz[1]), sz[2]);
    case 5: return Sqrt(sz[0] * sz[0] + sz[1] * sz[1]);
    case 6: return Sqrt(dot3(sz, sz));
  }
  return T(0);
}

// How far (m) the line o + s r passes outside the bounding sphere (<= 0: it passes through), with
// a margin for rounding: a ray with a positive gap cannot hit the geom.
template <typename T>
inline T bound_gap(const T* o, const T* r, T rb) {
  T rr = dot3(r, r), orr = dot3(o, r);
  return Sqrt(Max(dot3(o, o) - orr * orr / rr, T(0))) - rb * T(1.001) - T(1e-6);
}

// Whether the soft silhouette of a geom whose bounding sphere the ray misses by `gap` lies
// further than `margin` pixels away at any depth its closest approach can have: coverage there
// is below sigmoid(-margin / tau). (Not for ellipsoids, whose closest approach is taken in a
// scaled frame.)
template <typename T>
inline bool far_from(int t, const T* o, const T* r, T rb, T gap, T px, T near_, T margin) {
  if (t == 0 || t == 4 || !(gap > 0)) return false;
  T rr = dot3(r, r);
  T s_max = -dot3(o, r) / rr + rb / Sqrt(rr) * T(1.05) + T(1e-6);
  return gap > margin * Max(s_max, near_) * px;
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
    tau = 0, gamma = 1;  // per frame (begin_frame)
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

  bool culled(int t, int n) const { return t != 0 && n > Max(per_pixel, cull_above); }

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
        rad = Sqrt(Max(hh, T(0)));
        col = k;
      }
      T a[3], b[3];
      for (int i = 0; i < 3; ++i) {
        T e = half * m[3 * i + col];
        a[i] = c[i] - e, b[i] = c[i] + e;
      }
      T s_c, dist;
      line_segment(o, r, a, b, s_c, dist);
      T depth = Max(s_c, near_);
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
    dist = Sqrt(dot3(dl, dl) + T(1e-20));
    for (int k = 0; k < 3; ++k) l[k] = dl[k] / dist;
    factor = T(1) / (L[18] + L[19] * dist + L[20] * dist * dist);
    if (type == 0) {
      T cosang = -dot3(l, L + 4);
      bool inside = cosang >= cutoff_cos[i];
      factor = factor * (inside ? Exp(L[17] * Log(Max(cosang, T(1e-30)))) : T(0));
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
    T vn = Sqrt(dot3(v, v) + T(1e-20));
    for (int k = 0; k < 3; ++k) v[k] /= vn;
    T spec_m = spec[g], sh = T(128) * shin[g];
    for (int k = 0; k < 3; ++k) col[k] = emis[g] * alb[k];
    auto add = [&](const T* l, const T* amb, const T* dif, const T* spe, T factor) {
      T ndl = dot3(n, l);
      T h[3] = {l[0] + v[0], l[1] + v[1], l[2] + v[2]};
      T hn = Sqrt(dot3(h, h) + T(1e-20));
      for (int k = 0; k < 3; ++k) h[k] /= hn;
      T ndh = Max(dot3(n, h), T(0));
      T sp = ndl > 0 ? Exp(sh * Log(ndh + T(1e-30))) : T(0);
      T nd = Max(ndl, T(0));
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
    for (int k = 0; k < 3; ++k) col[k] = Min(Max(col[k], T(0)), T(1));
  }
};

// per-thread scratch, one entry per surface slot (a soft image has at most Scene::slots surfaces
// a pixel, a hard one every geom)
template <typename T>
struct Scratch {
  // per surface: first hit, depth where it is placed, coverage, depth then distance, world
  // point, point in the geom's frame (for its normal, found only where it is shaded), albedo
  std::vector<T> s_hit, s_n, cover, z, p, pl, alb, score;
  std::vector<T> rl, dist;     // per surface: the ray in the geom's frame, signed distance
  std::vector<int> gid, type, pick, lay;
  std::vector<int> skip;       // per surface: 1 the ray misses the bounding sphere, 2 far
                               // from the silhouette too (coverage < 1e-13: no search)
  std::vector<T> lit, ahead;
  std::vector<T> ol, oo, rb;  // per geom, per frame
  int64_t frame = -1;
  Scratch(int slots, int G, int NL) : lit(Max(NL, 1)), ol(3 * G), oo(G), rb(G) {
    const size_t S = Max(slots, G);
    for (auto* v : {&s_hit, &s_n, &cover, &z, &score, &dist}) v->resize(S);
    for (auto* v : {&p, &pl, &rl}) v->resize(3 * S);
    alb.resize(4 * S);
    ahead.resize(S * S);
    for (auto* v : {&gid, &type, &pick, &lay, &skip}) v->resize(S);
  }
};

// ahead[g * S + k]: how much surface k lies in front of surface g (soft: a sigmoid of their depth
// difference over gamma; hard: 0 or 1); only between two surfaces that both cover the pixel,
// the only pairs `composite` reads, unless every_pair (the reverse pass's composite_vjp reads
// them all)
template <typename T>
void depth_order(int S, const T* a, const T* z, bool soft, T gamma, T* ahead,
                 bool every_pair = false) {
  for (int g = 0; g < S; ++g)
    for (int k = g + 1; k < S; ++k) {
      if (!every_pair && (a[g] == 0 || a[k] == 0)) continue;
      if (soft) {
        T e = Exp((z[k] - z[g]) / gamma);  // sigmoid((z_g - z_k) / gamma) = 1 / (1 + e)
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

// A pixel's ray and what it meets, up to the surfaces it composites: each surface's hit, depth,
// distance, coverage, points; the first hit; the `layers` chosen (X.lay[0..L)).
template <typename T>
struct Ray {
  T r[3], fwd[3], px;
  int S, L, first;
  bool any_hit;
};

template <typename T>
void gather(const Scene<T>& sc, const T* cam, const T* geo, int i, int j, Scratch<T>& X,
            Ray<T>& R) {
  // X.ol / X.oo / X.rb: the camera in each geom's frame, its squared distance from the geom's
  // centre and the geom's bounding radius (per frame: set by the caller)
  const int G = sc.G;
  const bool soft = sc.tau != 0;
  const T* o = cam;
  const T* cm = cam + 3;
  T px = cam[12], cx = cam[13], cy = cam[14];
  T loc[3] = {(T(j) + T(0.5) - cx) * px, (cy - T(i) - T(0.5)) * px, T(-1)};
  T* r = R.r;
  for (int k = 0; k < 3; ++k) r[k] = (loc[0] * cm[3 * k] + loc[1] * cm[3 * k + 1]) + loc[2] * cm[3 * k + 2];
  for (int k = 0; k < 3; ++k) R.fwd[k] = -cm[3 * k + 2];
  R.px = px;
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
      T* rl = &X.rl[3 * S];
      to_local(r, xm, rl);
      T rb = X.rb[g];
      T gap = -1;
      if (t != 0) {  // does the ray miss the bounding sphere? (squared, no root)
        T rr = dot3(rl, rl), orr = dot3(ol, rl), rbm = rb * T(1.001) + T(1e-6);
        T miss = X.oo[g] * rr - orr * orr - rbm * rbm * rr;
        if (miss > 0) gap = soft ? bound_gap(ol, rl, rb) : T(1);
      }
      X.skip[S] = gap > 0 ? 1 : 0;
      T s_hit = gap > 0 ? K<T>::inf() : hit(t, ol, rl, sz);
      T sn, dist = 0;
      if (!soft) {
        sn = s_hit;
      } else if (far_from(t, ol, rl, rb, gap, px, sc.near_, T(30) * sc.tau)) {
        // the ray passes so far from the geom's bounding sphere that its coverage is under
        // sigmoid(-30) ~ 1e-13: nothing to search for; it adds nothing to the pixel
        sn = -dot3(ol, rl) / dot3(rl, rl);
        sn = Finite(sn) ? sn : sc.far_;
        dist = K<T>::inf();
        X.skip[S] = 2;
      } else {
        T s_c;
        closest(t, ol, rl, sz, sc.iters, s_c, dist);
        sn = Finite(s_hit) ? s_hit : s_c;
        sn = Finite(sn) ? sn : sc.far_;
      }
      // the normal is found only where the surface is shaded (draw_pixel's shading loop)
      T sp = soft ? sn : (Finite(s_hit) ? s_hit : sc.far_);
      for (int k = 0; k < 3; ++k) X.pl[3 * S + k] = ol[k] + sp * rl[k];
      X.s_hit[S] = (s_hit >= sc.near_ && s_hit <= sc.far_) ? s_hit : K<T>::inf();
      X.s_n[S] = sn;
      X.dist[S] = dist;
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
    any_hit |= Finite(X.s_hit[k]);
  }
  for (int k = 0; k < S; ++k) {
    bool h = Finite(X.s_hit[k]);
    T zk;
    if (!soft) {
      zk = h ? X.s_hit[k] : sc.far_;
      X.cover[k] = h ? T(1) : T(0);
    } else {
      zk = X.s_n[k];
      T d_px = X.dist[k] / (Max(zk, sc.near_) * px);
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
      if (X.cover[k] > T(0.999)) solid = Min(solid, X.z[k]);
    T* key = X.score.data();
    for (int k = 0; k < S; ++k) {
      bool shown = X.z[k] <= solid + (soft ? T(10) * sc.gamma : T(0));
      key[k] = shown ? X.cover[k] - T(1e-6) * X.z[k] / sc.far_ : T(-1) - X.z[k] / sc.far_;
    }
    top_k(key, S, sc.layers, lay);
    L = sc.layers;
  }
  R.S = S, R.L = L, R.first = first, R.any_hit = any_hit;
}

// A pixel's composite over its `layers` surfaces X.lay[0..L): coverage, depth, weights of the
// depth image (w, bg) and of the colour (wrgb: coverage times alpha), and the shadow factors.
template <typename T>
struct Mix {
  T a[64], zz[64], w[64], wa[64], wrgb[64], bg, bg_rgb;
};

template <typename T>
void mix(const Scene<T>& sc, const T* geo, Scratch<T>& X, const Ray<T>& R, Mix<T>& M) {
  const bool soft = sc.tau != 0;
  const int L = R.L;
  const int* lay = X.lay.data();
  for (int k = 0; k < L; ++k) M.a[k] = X.cover[lay[k]], M.zz[k] = X.z[lay[k]];
  T* ahead = X.ahead.data();
  depth_order(L, M.a, M.zz, soft, sc.gamma, ahead);
  composite(L, M.a, ahead, M.w, M.bg);
  T* lit = X.lit.data();
  if (sc.shadows && sc.any_shadow) {
    int win = 0;
    for (int k = 1; k < L; ++k)
      if (M.w[k] > M.w[win]) win = k;
    const T* pw = &X.p[3 * lay[win]];
    int gw = X.gid[lay[win]];
    for (int li = 0; li < sc.NL; ++li) {
      if (sc.light[li * kLightStride + 21] == 0) continue;
      T l[3], dist, factor;
      sc.light_dir(li, pw, l, dist, factor);
      lit[li] = sc.unoccluded(geo, pw, l, dist, gw);
    }
  }
  for (int k = 0; k < L; ++k) M.wa[k] = M.a[k] * X.alb[4 * lay[k] + 3];
  composite(L, M.wa, ahead, M.wrgb, M.bg_rgb);
}

// surface s's unit world normal n (and the local one, nl, and world nw it is made from)
template <typename T>
void surface_normal(const Scene<T>& sc, const T* geo, const Scratch<T>& X, const Ray<T>& R,
                    int s, T* nl, T* nw, T* n, T& nn) {
  const T* gp = geo + 19 * X.gid[s];
  normal(X.type[s], &X.pl[3 * s], gp + 12, sc.tau != 0, sc.tau * R.px * X.s_n[s], nl);
  to_world(nl, gp + 3, nw);
  nn = Sqrt(dot3(nw, nw) + T(1e-20));
  for (int q = 0; q < 3; ++q) n[q] = nw[q] / nn;
}

template <typename T>
void draw_pixel(const Scene<T>& sc, const T* cam, const T* geo, int i, int j, Scratch<T>& X,
                T* rgb, T* depth, int32_t* seg, int32_t* body, T* weights, T* background) {
  Ray<T> R;
  gather(sc, cam, geo, i, j, X, R);
  Mix<T> M;
  mix(sc, geo, X, R, M);
  const int L = R.L;
  const int* lay = X.lay.data();
  *seg = R.any_hit ? sc.gids[X.gid[R.first]] : -1;
  *body = R.any_hit ? sc.bodies[X.gid[R.first]] : -1;
  T out[3] = {0, 0, 0};
  for (int k = 0; k < L; ++k) {
    // a surface that adds nothing here is not shaded: the hard image's hidden ones (weight
    // exactly 0), the soft one's far from their silhouette (coverage under 1e-12)
    if (!(M.wrgb[k] > T(1e-12))) continue;
    int s = lay[k];
    T nl[3], nw[3], n[3], nn, col[3];
    surface_normal(sc, geo, X, R, s, nl, nw, n, nn);
    sc.shade(&X.p[3 * s], n, cam, R.fwd, &X.alb[4 * s], X.gid[s], X.lit.data(), col);
    for (int q = 0; q < 3; ++q) out[q] = out[q] + M.wrgb[k] * col[q];
  }
  for (int q = 0; q < 3; ++q) rgb[q] = out[q];
  if (sc.tau != 0) {
    T dsum = 0;
    for (int k = 0; k < L; ++k) dsum = k == 0 ? M.w[0] * M.zz[0] : dsum + M.w[k] * M.zz[k];
    *depth = dsum + M.bg * sc.far_depth;
  } else {
    *depth = R.any_hit ? X.s_hit[R.first] : sc.far_depth;
  }
  for (int g = 0; g < sc.G; ++g) weights[g] = 0;
  for (int k = 0; k < L; ++k) weights[X.gid[lay[k]]] += M.w[k];
  *background = M.bg;
}

// ------------------------------------------------------------------ the reverse pass
// The gradient of <cotangent, image> with respect to the camera and the geoms, pixel by pixel:
// the pixel is drawn again (gather, mix), then differentiated backwards by hand through the
// composite and the shading down to each surface's depth, distance and normal, and from those
// to the surface's inputs (the ray and camera in the geom's frame, its size, the pixel size)
// through that surface's Jacobian, found on Dual numbers by the same templates that drew it.

// the composite's reverse (every pair, as JAX takes them: a pair with a zero coverage has
// occlusion exactly 1 either way, but its derivative need not be 0)
template <typename T>
void composite_vjp(int L, const T* a, const T* ahead, const T* dw, T dbg, T* da, T* dahead) {
  T occl[64 * 64], P[64], u[64];
  T B = 1, tot = 0;
  for (int g = 0; g < L; ++g) {
    T prod = 1;
    for (int k = 0; k < L; ++k) {
      T o = k == g ? T(1) : T(1) - a[k] * ahead[g * L + k];
      occl[g * L + k] = o;
      prod = k == 0 ? o : prod * o;
    }
    P[g] = prod;
    u[g] = a[g] * prod;
    tot = g == 0 ? u[0] : tot + u[g];
    B = g == 0 ? T(1) - a[0] : B * (T(1) - a[g]);
  }
  tot = tot + B;
  bool pos = tot > 0;
  T t = pos ? tot : T(1);
  T dtot = 0;
  if (pos) {
    for (int g = 0; g < L; ++g) dtot -= dw[g] * u[g];
    dtot = (dtot - dbg * B) / (t * t);
  }
  T dB = dbg / t + dtot;
  T pre[65], suf[65];
  for (int g = 0; g < L; ++g) {
    T du = dw[g] / t + dtot;
    da[g] += du * P[g];
    T coef = du * a[g];
    if (coef == 0) continue;
    const T* og = &occl[g * L];
    pre[0] = 1;
    for (int k = 0; k < L; ++k) pre[k + 1] = pre[k] * og[k];
    suf[L] = 1;
    for (int k = L - 1; k >= 0; --k) suf[k] = suf[k + 1] * og[k];
    for (int k = 0; k < L; ++k) {
      if (k == g) continue;
      T d_o = coef * pre[k] * suf[k + 1];
      da[k] -= d_o * ahead[g * L + k];
      dahead[g * L + k] -= d_o * a[k];
    }
  }
  if (dB != 0) {
    pre[0] = 1;
    for (int k = 0; k < L; ++k) pre[k + 1] = pre[k] * (T(1) - a[k]);
    suf[L] = 1;
    for (int k = L - 1; k >= 0; --k) suf[k] = suf[k + 1] * (T(1) - a[k]);
    for (int k = 0; k < L; ++k) da[k] -= dB * pre[k] * suf[k + 1];
  }
}

// d clip(x, 0, 1) / dx as JAX's (ties half)
template <typename T>
inline T clip_slope(T x) {
  T lo = x > 0 ? T(1) : (x == 0 ? T(0.5) : T(0));
  T hi = x < 1 ? T(1) : (x == 1 ? T(0.5) : T(0));
  return lo * hi;
}
template <typename T>
inline T relu_slope(T x) { return x > 0 ? T(1) : (x == 0 ? T(0.5) : T(0)); }

// the reverse of x / sqrt(x.x + 1e-20) (y, its value; nn, the root): dx from dy
template <typename T>
inline void unit_vjp(const T* y, T nn, const T* dy, T* dx) {
  T yd = dot3(y, dy);
  for (int k = 0; k < 3; ++k) dx[k] += (dy[k] - y[k] * yd) / nn;
}

// Scene::shade's reverse: dcol (the clamped colour's cotangent) to p, n, the camera position o,
// the view direction fwd and the albedo's rgb (all added to); out: the colour Scene::shade gives
template <typename T>
void shade_vjp(const Scene<T>& sc, const T* p, const T* n, const T* o, const T* fwd,
               const T* alb, int g, const T* lit, const T* dcol_clamped, T* dp, T* dn, T* d_o,
               T* dfwd, T* dalb, T* out) {
  T col[3];
  T v0[3];
  for (int k = 0; k < 3; ++k) v0[k] = o[k] - p[k];
  T vn = Sqrt(dot3(v0, v0) + T(1e-20));
  T v[3] = {v0[0] / vn, v0[1] / vn, v0[2] / vn};
  T spec_m = sc.spec[g], sh = T(128) * sc.shin[g];
  // the unclamped colour (to know where the clamp passes the gradient)
  for (int k = 0; k < 3; ++k) col[k] = sc.emis[g] * alb[k];
  auto light_terms = [&](const T* l, T& ndl, T* h, T& hn, T* h0, T& ndh, T& nh, T& sp, T& nd) {
    ndl = dot3(n, l);
    for (int k = 0; k < 3; ++k) h0[k] = l[k] + v[k];
    hn = Sqrt(dot3(h0, h0) + T(1e-20));
    for (int k = 0; k < 3; ++k) h[k] = h0[k] / hn;
    nh = dot3(n, h);
    ndh = Max(nh, T(0));
    sp = ndl > 0 ? Exp(sh * Log(ndh + T(1e-30))) : T(0);
    nd = Max(ndl, T(0));
  };
  // light q (the headlight first where it is on): direction, factor (shadow included), colours
  struct LightEval {
    T l[3], factor;
    const T *amb, *dif, *spe;
    int kind;  // 0 headlight, 1 directional, 2 point or spot
    int index;
  };
  const int ne = sc.NL + (sc.head_on ? 1 : 0);
  auto eval = [&](int q, LightEval& e) {
    if (sc.head_on && q == 0) {
      for (int k = 0; k < 3; ++k) e.l[k] = -fwd[k];
      e.amb = sc.head, e.dif = sc.head + 3, e.spe = sc.head + 6;
      e.factor = 1, e.kind = 0, e.index = -1;
      return;
    }
    int i = q - (sc.head_on ? 1 : 0);
    const T* L = &sc.light[i * kLightStride];
    T dist;
    sc.light_dir(i, p, e.l, dist, e.factor);
    if (sc.shadows && L[21] != 0) e.factor = e.factor * lit[i];
    e.amb = L + 7, e.dif = L + 10, e.spe = L + 13;
    e.kind = int(L[0]) == 1 ? 1 : 2;
    e.index = i;
  };
  for (int q = 0; q < ne; ++q) {
    LightEval e;
    eval(q, e);
    T ndl, h[3], hn, h0[3], ndh, nh, sp, nd;
    light_terms(e.l, ndl, h, hn, h0, ndh, nh, sp, nd);
    for (int k = 0; k < 3; ++k)
      col[k] = col[k] + e.amb[k] * alb[k] +
               e.factor * (e.dif[k] * nd * alb[k] + e.spe[k] * spec_m * sp);
  }
  T dcol[3];
  for (int k = 0; k < 3; ++k) {
    dcol[k] = dcol_clamped[k] * clip_slope(col[k]);
    out[k] = Min(Max(col[k], T(0)), T(1));
  }
  if (dcol[0] == 0 && dcol[1] == 0 && dcol[2] == 0) return;
  T dv[3] = {0, 0, 0};
  for (int k = 0; k < 3; ++k) dalb[k] += dcol[k] * sc.emis[g];
  for (int q = 0; q < ne; ++q) {
    LightEval e;
    eval(q, e);
    T ndl, h[3], hn, h0[3], ndh, nh, sp, nd;
    light_terms(e.l, ndl, h, hn, h0, ndh, nh, sp, nd);
    T dfactor = 0, dnd = 0, dsp = 0;
    for (int k = 0; k < 3; ++k) {
      dalb[k] += dcol[k] * (e.amb[k] + e.factor * e.dif[k] * nd);
      dfactor += dcol[k] * (e.dif[k] * nd * alb[k] + e.spe[k] * spec_m * sp);
      dnd += dcol[k] * e.dif[k] * alb[k];
      dsp += dcol[k] * e.spe[k];
    }
    dnd *= e.factor;
    dsp *= e.factor * spec_m;
    T dndl = dnd * relu_slope(ndl);
    T dndh = ndl > 0 ? dsp * sp * sh / (ndh + T(1e-30)) : T(0);
    T dnh = dndh * relu_slope(nh);
    T dl[3], dh0[3] = {0, 0, 0};
    T dh[3];
    for (int k = 0; k < 3; ++k) {
      dn[k] += dnh * h[k] + dndl * e.l[k];
      dh[k] = dnh * n[k];
      dl[k] = dndl * n[k];
    }
    unit_vjp(h, hn, dh, dh0);
    for (int k = 0; k < 3; ++k) dl[k] += dh0[k], dv[k] += dh0[k];
    if (e.kind == 0) {
      for (int k = 0; k < 3; ++k) dfwd[k] -= dl[k];
    } else if (e.kind == 2) {
      // l = (pos - p) / dist, factor = lit / (a0 + a1 dist + a2 dist^2) [x spot(cos)]
      const T* L = &sc.light[e.index * kLightStride];
      T dlv[3];
      for (int k = 0; k < 3; ++k) dlv[k] = L[1 + k] - p[k];
      T dist = Sqrt(dot3(dlv, dlv) + T(1e-20));
      T f0 = T(1) / (L[18] + L[19] * dist + L[20] * dist * dist);
      T shadow = (sc.shadows && L[21] != 0) ? lit[e.index] : T(1);
      T spot = 1;
      if (int(L[0]) == 0) {
        T cosang = -dot3(e.l, L + 4);
        bool inside = cosang >= sc.cutoff_cos[e.index];
        spot = inside ? Exp(L[17] * Log(Max(cosang, T(1e-30)))) : T(0);
        T dspot = dfactor * f0 * shadow;
        T dcos = (inside && cosang > T(1e-30)) ? dspot * spot * L[17] / cosang : T(0);
        for (int k = 0; k < 3; ++k) dl[k] -= dcos * L[4 + k];
      }
      T df0 = dfactor * spot * shadow;
      T ddist = -df0 * f0 * f0 * (L[19] + T(2) * L[20] * dist);
      T ldl = dot3(dl, dlv);
      T ddlv[3];
      for (int k = 0; k < 3; ++k) {
        ddlv[k] = dl[k] / dist;
      }
      ddist -= ldl / (dist * dist);
      for (int k = 0; k < 3; ++k) dp[k] -= ddlv[k] + ddist * dlv[k] / dist;
    }
  }
  T dv0[3] = {0, 0, 0};
  unit_vjp(v, vn, dv, dv0);
  for (int k = 0; k < 3; ++k) d_o[k] += dv0[k], dp[k] -= dv0[k];
}

constexpr int kIn = 10;  // a surface's inputs: the camera (3) and ray (3) in the geom's frame,
                         // the geom's size (3), the pixel size

// Surface s's Jacobian applied to the cotangents of its first hit, placed depth, signed distance
// and local normal: the cotangents of its kIn inputs (g_in, overwritten)
template <typename T>
void surface_vjp(const Scene<T>& sc, const T* geo, const Scratch<T>& X, T px, int s, T d_hit,
                 T d_sn, T d_dist, const T* d_nl, bool normal_needed, T* g_in) {
  using D = Dual<T, kIn>;
  const bool soft = sc.tau != 0;
  const int t = X.type[s];
  const T* gp = geo + 19 * X.gid[s];
  const T* ol = &X.ol[3 * X.gid[s]];
  const T* rlv = &X.rl[3 * s];
  D o[3], r[3], sz[3];
  for (int k = 0; k < 3; ++k) {
    o[k] = D::seed(ol[k], k);
    r[k] = D::seed(rlv[k], 3 + k);
    sz[k] = D::seed(gp[12 + k], 6 + k);
  }
  D P = D::seed(px, 9);
  const T inf = K<T>::inf();
  D s_hit = X.skip[s] ? D(inf) : hit(t, o, r, sz);
  D sn, dist(0.0);
  if (!soft) {
    sn = s_hit;
  } else if (d_dist == 0 && Finite(s_hit)) {
    sn = s_hit;  // the closest approach would only give the distance, which nothing needs
  } else {
    D s_c;
    closest(t, o, r, sz, sc.iters, s_c, dist);
    sn = Finite(s_hit) ? s_hit : s_c;
    sn = Finite(sn) ? sn : D(value(sc.far_));
  }
  for (int k = 0; k < kIn; ++k) g_in[k] = 0;
  auto add = [&](const D& x, T c) {
    if (c != 0)
      for (int k = 0; k < kIn; ++k) g_in[k] += c * x.d[k];
  };
  add(s_hit, d_hit);
  add(sn, d_sn);
  add(dist, d_dist);
  if (normal_needed) {
    D sp = soft ? sn : (Finite(s_hit) ? s_hit : D(value(sc.far_)));
    D pl[3], nl[3];
    for (int k = 0; k < 3; ++k) pl[k] = o[k] + sp * r[k];
    D tn = D(value(sc.tau)) * P * sn;
    normal(t, pl, sz, soft, tn, nl);
    for (int k = 0; k < 3; ++k) add(nl[k], d_nl[k]);
  }
}

template <typename T>
void draw_pixel_vjp(const Scene<T>& sc, const T* cam, const T* geo, int i, int j, Scratch<T>& X,
                    const T* c_rgb, T c_depth, const T* c_w, T c_bg, T* gcam, T* ggeo) {
  const bool soft = sc.tau != 0;
  Ray<T> R;
  gather(sc, cam, geo, i, j, X, R);
  Mix<T> M;
  mix(sc, geo, X, R, M);
  const int L = R.L, S = R.S;
  const int* lay = X.lay.data();
  const T* r = R.r;
  // cotangents per layer and per surface
  T d_w[64], d_zz[64], d_a[64], d_wa[64], d_wrgb[64];
  T d_hit[64], d_sn[64], d_dist[64], d_z[64], d_nl[3 * 64];
  bool shaded[64];
  for (int k = 0; k < S; ++k) {
    d_hit[k] = d_sn[k] = d_dist[k] = d_z[k] = 0;
    d_nl[3 * k] = d_nl[3 * k + 1] = d_nl[3 * k + 2] = 0;
    shaded[k] = false;
  }
  T d_bg = c_bg;
  for (int k = 0; k < L; ++k) {
    d_w[k] = c_w[X.gid[lay[k]]];
    d_zz[k] = d_a[k] = d_wa[k] = d_wrgb[k] = 0;
  }
  if (soft) {
    for (int k = 0; k < L; ++k) d_w[k] += c_depth * M.zz[k], d_zz[k] += c_depth * M.w[k];
    d_bg += c_depth * sc.far_depth;
  } else if (R.any_hit) {
    d_hit[R.first] += c_depth;
  }
  T d_o[3] = {0, 0, 0}, d_r[3] = {0, 0, 0}, d_fwd[3] = {0, 0, 0}, d_px = 0;
  for (int k = 0; k < L; ++k) {
    // A surface's colour matters where it is drawn (wrgb) and, through the derivative of its
    // weight, wherever it covers the pixel (wa): hidden behind an opaque one, its colour is
    // what that one's alpha lets through. (Under 1e-12 either way, nothing is lost.)
    if (!(M.wa[k] > T(1e-12))) continue;
    int s = lay[k];
    int g = X.gid[s];
    T* gg = ggeo + 19 * g;
    const T* gp = geo + 19 * g;
    T nl[3], nw[3], n[3], nn, col[3];
    surface_normal(sc, geo, X, R, s, nl, nw, n, nn);
    if (!(M.wrgb[k] > T(1e-12))) {
      sc.shade(&X.p[3 * s], n, cam, R.fwd, &X.alb[4 * s], g, X.lit.data(), col);
      d_wrgb[k] = dot3(c_rgb, col);
      continue;
    }
    T dcol[3] = {M.wrgb[k] * c_rgb[0], M.wrgb[k] * c_rgb[1], M.wrgb[k] * c_rgb[2]};
    T dp[3] = {0, 0, 0}, dn[3] = {0, 0, 0}, dalb[3] = {0, 0, 0};
    shade_vjp(sc, &X.p[3 * s], n, cam, R.fwd, &X.alb[4 * s], g, X.lit.data(), dcol, dp, dn, d_o,
              d_fwd, dalb, col);
    d_wrgb[k] = dot3(c_rgb, col);
    for (int q = 0; q < 3; ++q) gg[15 + q] += dalb[q];
    T dnw[3] = {0, 0, 0};
    unit_vjp(n, nn, dn, dnw);
    for (int a = 0; a < 3; ++a)
      for (int b = 0; b < 3; ++b) {
        d_nl[3 * s + b] += dnw[a] * gp[3 + 3 * a + b];
        gg[3 + 3 * a + b] += dnw[a] * nl[b];
      }
    shaded[s] = true;
    // p = o + z r
    for (int q = 0; q < 3; ++q) d_o[q] += dp[q], d_r[q] += X.z[s] * dp[q];
    d_z[s] += dot3(dp, r);
  }
  // the composites (the depth image's only where soft: the hard one's weights are constants)
  T* ahead = X.ahead.data();
  depth_order(L, M.a, M.zz, soft, sc.gamma, ahead, true);
  T dahead[64 * 64];
  for (int q = 0; q < L * L; ++q) dahead[q] = 0;
  composite_vjp(L, M.wa, ahead, d_wrgb, T(0), d_wa, dahead);
  for (int k = 0; k < L; ++k) {
    int s = lay[k];
    ggeo[19 * X.gid[s] + 18] += d_wa[k] * M.a[k];
    d_a[k] += d_wa[k] * X.alb[4 * s + 3];
  }
  if (soft) {
    composite_vjp(L, M.a, ahead, d_w, d_bg, d_a, dahead);
    for (int g = 0; g < L; ++g)
      for (int k = g + 1; k < L; ++k) {
        T h = ahead[g * L + k];
        T dz = (dahead[g * L + k] - dahead[k * L + g]) * h * (T(1) - h) / sc.gamma;
        d_zz[g] += dz, d_zz[k] -= dz;
      }
    for (int k = 0; k < L; ++k) {
      int s = lay[k];
      d_z[s] += d_zz[k];
      T c = X.cover[s];
      // masked (outside near..far), or so far in or out that the sigmoid is flat: a derivative
      // under 1e-10 of the others (and the distance need not be differentiated at all)
      if (!(c * (T(1) - c) > T(1e-10))) continue;
      T M_ = Max(X.s_n[s], sc.near_);
      T den = M_ * R.px * sc.tau;
      T dx = d_a[k] * c * (T(1) - c);
      d_dist[s] += -dx / den;
      T dM = dx * X.dist[s] / (den * M_);
      d_sn[s] += dM * relu_slope(X.s_n[s] - sc.near_);
      d_px += dx * X.dist[s] / (den * R.px);
    }
    for (int s = 0; s < S; ++s) {
      d_sn[s] += d_z[s];
      if (!(X.cover[s] > T(1e-10)) && !shaded[s]) d_sn[s] = 0;  // adds nothing to the pixel
    }
  } else {
    for (int s = 0; s < S; ++s)
      if (Finite(X.s_hit[s])) d_hit[s] += d_z[s];
  }
  // each surface's inputs
  for (int s = 0; s < S; ++s) {
    bool any = d_hit[s] != 0 || d_sn[s] != 0 || d_dist[s] != 0 || shaded[s];
    if (!any || X.skip[s] == 2) continue;
    T g_in[kIn];
    surface_vjp(sc, geo, X, R.px, s, d_hit[s], d_sn[s], d_dist[s], &d_nl[3 * s], shaded[s],
                g_in);
    int g = X.gid[s];
    T* gg = ggeo + 19 * g;
    const T* gp = geo + 19 * g;
    for (int a = 0; a < 3; ++a) {
      T t_o = 0, t_r = 0;
      for (int b = 0; b < 3; ++b) {
        T m = gp[3 + 3 * a + b];
        t_o += g_in[b] * m;
        t_r += g_in[3 + b] * m;
        gg[3 + 3 * a + b] += (cam[a] - gp[a]) * g_in[b] + r[a] * g_in[3 + b];
      }
      d_o[a] += t_o;
      gg[a] -= t_o;
      d_r[a] += t_r;
      gg[12 + a] += g_in[6 + a];
    }
    d_px += g_in[9];
  }
  // the ray r = cm loc, loc = ((j + 0.5 - cx) px, (cy - i - 0.5) px, -1); fwd = -cm[:, 2]
  const T* cm = cam + 3;
  T px = cam[12], cx = cam[13], cy = cam[14];
  T loc[3] = {(T(j) + T(0.5) - cx) * px, (cy - T(i) - T(0.5)) * px, T(-1)};
  T dloc[3] = {0, 0, 0};
  for (int a = 0; a < 3; ++a)
    for (int c = 0; c < 3; ++c) {
      gcam[3 + 3 * a + c] += d_r[a] * loc[c];
      dloc[c] += d_r[a] * cm[3 * a + c];
    }
  for (int a = 0; a < 3; ++a) gcam[3 + 3 * a + 2] -= d_fwd[a], gcam[a] += d_o[a];
  d_px += dloc[0] * (T(j) + T(0.5) - cx) + dloc[1] * (cy - T(i) - T(0.5));
  gcam[12] += d_px;
  gcam[13] -= dloc[0] * px;
  gcam[14] += dloc[1] * px;
}

int worker_count(int64_t rows) {
  int n = 1;
#if defined(__linux__)
  cpu_set_t set;
  if (sched_getaffinity(0, sizeof(set), &set) == 0) n = CPU_COUNT(&set);
#else
  n = int(std::thread::hardware_concurrency());
#endif
  if (const char* env = std::getenv("TWINRL_RENDER_THREADS")) n = Max(1, std::atoi(env));
  return int(std::max<int64_t>(1, std::min<int64_t>(n, rows)));
}

// run(worker, r0, r1) on nw workers, rows [0, rows) split evenly; this thread is worker 0
template <typename F>
void parallel_rows(int nw, int64_t rows, const F& run) {
  if (nw == 1) {
    run(0, 0, rows);
    return;
  }
  std::vector<std::thread> pool;
  for (int k = 1; k < nw; ++k)
    pool.emplace_back([&run, k, nw, rows] { run(k, rows * k / nw, rows * (k + 1) / nw); });
  run(0, 0, rows / nw);
  for (auto& t : pool) t.join();
}

// A worker's set-up for frame b: its temperatures (tg: tau, gamma per frame, so that a batch
// may anneal them or trace them), the camera in each geom's frame, the bounding radii
template <typename T>
void begin_frame(Scene<T>& sc, Scratch<T>& X, const T* c, const T* g, const T* tg, int64_t b) {
  if (X.frame == b) return;
  sc.tau = tg[2 * b], sc.gamma = tg[2 * b + 1];
  for (int k = 0; k < sc.G; ++k) {
    const T* gp = g + 19 * k;
    T d[3] = {c[0] - gp[0], c[1] - gp[1], c[2] - gp[2]};
    to_local(d, gp + 3, &X.ol[3 * k]);
    X.oo[k] = dot3(&X.ol[3 * k], &X.ol[3 * k]);
    X.rb[k] = bound_radius(sc.types[k], gp + 12);
  }
  X.frame = b;
}

// pixel(worker, scene, scratch, cam, geo, frame, row, column, index) for every pixel of the
// batch, the rows split over nw workers, each with its own copy of the scene (its frames'
// temperatures) and its own scratch
template <typename T, typename F>
void for_pixels(const Scene<T>& sc, const T* camp, const T* geop, const T* tgp, int64_t N,
                int64_t H, int64_t W, int nw, const F& pixel) {
  parallel_rows(nw, N * H, [&](int worker, int64_t r0, int64_t r1) {
    Scene<T> S = sc;
    Scratch<T> X(sc.slots, sc.G, sc.NL);
    for (int64_t row = r0; row < r1; ++row) {
      int64_t b = row / H, i = row % H;
      const T* c = camp + 15 * b;
      const T* g = geop + int64_t(19) * sc.G * b;
      begin_frame(S, X, c, g, tgp, b);
      for (int64_t j = 0; j < W; ++j)
        pixel(worker, S, X, c, g, b, int(i), int(j), (b * H + i) * W + j);
    }
  });
}

template <typename T, ffi::DataType DT>
ffi::Error Render(ffi::Buffer<DT> cam, ffi::Buffer<DT> geo, ffi::Buffer<DT> tg,
                  ffi::ResultBuffer<DT> rgb,
                  ffi::ResultBuffer<DT> depth, ffi::ResultBuffer<ffi::S32> seg,
                  ffi::ResultBuffer<ffi::S32> body, ffi::ResultBuffer<DT> weights,
                  ffi::ResultBuffer<DT> background, Config cfg) {
  Scene<T> sc(cfg);
  auto dims = rgb->dimensions();
  if (dims.size() < 3) return ffi::Error::InvalidArgument("rgb must be (..., H, W, 3)");
  const int64_t H = dims[dims.size() - 3], W = dims[dims.size() - 2];
  const int64_t N = int64_t(rgb->element_count()) / (H * W * 3);
  const int G = sc.G;
  if (int64_t(cam.element_count()) != N * 15 || int64_t(geo.element_count()) != N * G * 19 ||
      int64_t(tg.element_count()) != N * 2)
    return ffi::Error::InvalidArgument("camera, geom or temperature batch does not match");
  if (sc.slots > 64 || G > 64)
    return ffi::Error::InvalidArgument("more than 64 geoms or surfaces a pixel");
  const T* camp = cam.typed_data();
  const T* geop = geo.typed_data();
  const T* tgp = tg.typed_data();
  T* rgbp = rgb->typed_data();
  T* depp = depth->typed_data();
  int32_t* segp = seg->typed_data();
  int32_t* bodp = body->typed_data();
  T* wp = weights->typed_data();
  T* bgp = background->typed_data();
  for_pixels(sc, camp, geop, tgp, N, H, W, worker_count(N * H),
             [&](int, const Scene<T>& S, Scratch<T>& X, const T* c, const T* g, int64_t, int i,
                 int j, int64_t px) {
               draw_pixel(S, c, g, i, j, X, rgbp + 3 * px, depp + px, segp + px, bodp + px,
                          wp + int64_t(G) * px, bgp + px);
             });
  return ffi::Error::Success();
}


// The reverse kernel: cotangents of rgb (..., H, W, 3), depth, weights (..., H, W, G) and
// background to those of cam (..., 15) and geo (..., G, 19). Each worker adds its rows' pixels
// into its own copy of the gradients; the copies are summed at the end.
template <typename T, ffi::DataType DT>
ffi::Error RenderVjp(ffi::Buffer<DT> cam, ffi::Buffer<DT> geo, ffi::Buffer<DT> tg,
                     ffi::Buffer<DT> c_rgb,
                     ffi::Buffer<DT> c_depth, ffi::Buffer<DT> c_w, ffi::Buffer<DT> c_bg,
                     ffi::ResultBuffer<DT> gcam, ffi::ResultBuffer<DT> ggeo, Config cfg) {
  Scene<T> sc(cfg);
  auto dims = c_rgb.dimensions();
  if (dims.size() < 3) return ffi::Error::InvalidArgument("rgb must be (..., H, W, 3)");
  const int64_t H = dims[dims.size() - 3], W = dims[dims.size() - 2];
  const int64_t N = int64_t(c_rgb.element_count()) / (H * W * 3);
  const int G = sc.G;
  if (int64_t(cam.element_count()) != N * 15 || int64_t(geo.element_count()) != N * G * 19 ||
      int64_t(tg.element_count()) != N * 2 || int64_t(c_w.element_count()) != N * H * W * G)
    return ffi::Error::InvalidArgument("camera, geom or cotangent batch does not match");
  if (sc.slots > 64 || G > 64)
    return ffi::Error::InvalidArgument("more than 64 geoms or surfaces a pixel");
  const T* camp = cam.typed_data();
  const T* geop = geo.typed_data();
  const T* tgp = tg.typed_data();
  const T* crgb = c_rgb.typed_data();
  const T* cdep = c_depth.typed_data();
  const T* cw = c_w.typed_data();
  const T* cbg = c_bg.typed_data();
  const int64_t rows = N * H;
  const int64_t ncam = N * 15, ngeo = N * G * 19;
  int nw = worker_count(rows);
  std::vector<std::vector<T>> acc(nw, std::vector<T>(ncam + ngeo, T(0)));
  for_pixels(sc, camp, geop, tgp, N, H, W, nw,
             [&](int worker, const Scene<T>& S, Scratch<T>& X, const T* c, const T* g,
                 int64_t b, int i, int j, int64_t px) {
               const T* cr = crgb + 3 * px;
               const T* cwp = cw + int64_t(G) * px;
               bool zero = cr[0] == 0 && cr[1] == 0 && cr[2] == 0 && cdep[px] == 0 &&
                           cbg[px] == 0;
               for (int k = 0; zero && k < G; ++k) zero = cwp[k] == 0;
               if (zero) return;  // (a crop's loss, a masked pixel)
               T* gc = acc[worker].data();
               draw_pixel_vjp(S, c, g, i, j, X, cr, cdep[px], cwp, cbg[px], gc + 15 * b,
                              gc + ncam + int64_t(19) * G * b);
             });
  T* oc = gcam->typed_data();
  T* og = ggeo->typed_data();
  for (int64_t q = 0; q < ncam; ++q) {
    T x = 0;
    for (int w = 0; w < nw; ++w) x += acc[w][q];
    oc[q] = x;
  }
  for (int64_t q = 0; q < ngeo; ++q) {
    T x = 0;
    for (int w = 0; w < nw; ++w) x += acc[w][ncam + q];
    og[q] = x;
  }
  return ffi::Error::Success();
}

}  // namespace

// the scene's attributes (Config), in both kernels' bindings
#define TWINRL_ATTRS                                      \
  .Attr<ffi::Span<const int32_t>>("types")                \
      .Attr<ffi::Span<const int32_t>>("gids")             \
      .Attr<ffi::Span<const int32_t>>("bodies")           \
      .Attr<ffi::Span<const int32_t>>("opts")             \
      .Attr<ffi::Span<const double>>("mat")               \
      .Attr<ffi::Span<const double>>("lights")            \
      .Attr<ffi::Span<const double>>("headlight")         \
      .Attr<ffi::Span<const double>>("scal")

#define TWINRL_BIND(DT)                                   \
  ffi::Ffi::Bind()                                        \
      .Arg<ffi::Buffer<DT>>()                             \
      .Arg<ffi::Buffer<DT>>()                             \
      .Arg<ffi::Buffer<DT>>()                             \
      .Ret<ffi::Buffer<DT>>()                             \
      .Ret<ffi::Buffer<DT>>()                             \
      .Ret<ffi::Buffer<ffi::S32>>()                       \
      .Ret<ffi::Buffer<ffi::S32>>()                       \
      .Ret<ffi::Buffer<DT>>()                             \
      .Ret<ffi::Buffer<DT>>()                             \
      TWINRL_ATTRS

template <typename T, ffi::DataType DT>
static ffi::Error RenderEntry(ffi::Buffer<DT> cam, ffi::Buffer<DT> geo, ffi::Buffer<DT> tg,
                              ffi::ResultBuffer<DT> rgb, ffi::ResultBuffer<DT> depth,
                              ffi::ResultBuffer<ffi::S32> seg, ffi::ResultBuffer<ffi::S32> body,
                              ffi::ResultBuffer<DT> weights, ffi::ResultBuffer<DT> background,
                              ffi::Span<const int32_t> types, ffi::Span<const int32_t> gids,
                              ffi::Span<const int32_t> bodies, ffi::Span<const int32_t> opts,
                              ffi::Span<const double> mat, ffi::Span<const double> lights,
                              ffi::Span<const double> headlight, ffi::Span<const double> scal) {
  Config cfg{types, gids, bodies, opts, mat, lights, headlight, scal};
  return Render<T, DT>(cam, geo, tg, rgb, depth, seg, body, weights, background, cfg);
}

XLA_FFI_DEFINE_HANDLER_SYMBOL(TwinrlRenderF32, (RenderEntry<float, ffi::F32>), TWINRL_BIND(ffi::F32));
XLA_FFI_DEFINE_HANDLER_SYMBOL(TwinrlRenderF64, (RenderEntry<double, ffi::F64>), TWINRL_BIND(ffi::F64));

#define TWINRL_BIND_VJP(DT)                               \
  ffi::Ffi::Bind()                                        \
      .Arg<ffi::Buffer<DT>>()                             \
      .Arg<ffi::Buffer<DT>>()                             \
      .Arg<ffi::Buffer<DT>>()                             \
      .Arg<ffi::Buffer<DT>>()                             \
      .Arg<ffi::Buffer<DT>>()                             \
      .Arg<ffi::Buffer<DT>>()                             \
      .Arg<ffi::Buffer<DT>>()                             \
      .Ret<ffi::Buffer<DT>>()                             \
      .Ret<ffi::Buffer<DT>>()                             \
      TWINRL_ATTRS

template <typename T, ffi::DataType DT>
static ffi::Error RenderVjpEntry(ffi::Buffer<DT> cam, ffi::Buffer<DT> geo, ffi::Buffer<DT> tg,
                                 ffi::Buffer<DT> c_rgb,
                                 ffi::Buffer<DT> c_depth, ffi::Buffer<DT> c_w,
                                 ffi::Buffer<DT> c_bg, ffi::ResultBuffer<DT> gcam,
                                 ffi::ResultBuffer<DT> ggeo, ffi::Span<const int32_t> types,
                                 ffi::Span<const int32_t> gids, ffi::Span<const int32_t> bodies,
                                 ffi::Span<const int32_t> opts, ffi::Span<const double> mat,
                                 ffi::Span<const double> lights,
                                 ffi::Span<const double> headlight,
                                 ffi::Span<const double> scal) {
  Config cfg{types, gids, bodies, opts, mat, lights, headlight, scal};
  return RenderVjp<T, DT>(cam, geo, tg, c_rgb, c_depth, c_w, c_bg, gcam, ggeo, cfg);
}

XLA_FFI_DEFINE_HANDLER_SYMBOL(TwinrlRenderVjpF32, (RenderVjpEntry<float, ffi::F32>),
                              TWINRL_BIND_VJP(ffi::F32));
XLA_FFI_DEFINE_HANDLER_SYMBOL(TwinrlRenderVjpF64, (RenderVjpEntry<double, ffi::F64>),
                              TWINRL_BIND_VJP(ffi::F64));
