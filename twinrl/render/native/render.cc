// The renderer's image and its reverse pass, as XLA FFI custom calls on the CPU.
//
// The same arithmetic as twinrl/render/image.py's render_jax and primitives.py (read
// those for the why of each step): rays from a pinhole camera, each drawn primitive's first hit
// and (soft image) closest approach and normal in its local frame, per-pixel culling of crowded
// types, the `layers` most covering surfaces, front-to-back compositing with a smooth depth
// order, hard shadow rays and OpenGL's fixed-function shading. XLA runs the JAX version as
// hundreds of passes over (pixel, surface) arrays; here a packet of pixels (a small tile, one
// pixel a SIMD lane: 16 float32 lanes where the CPU has AVX-512) is drawn start to finish in
// registers, the frames' tile rows split across the CPU's cores. Every step is written for all
// lanes at once: a branch of the per-pixel arithmetic is a lane mask and a select. Work no lane
// needs is skipped for the whole packet: a geom that no ray of the packet's 16x16 block passes
// near (block_geoms), a surface no lane needs (a slot is made only where some lane's ray may hit
// it, or passes near its silhouette), a surface no pixel shows. Every slot is one geom for all
// lanes, geometry runs per slot (one primitive type); what differs between a packet's pixels is
// a lane mask: the crowded types' geoms culling picks (a slot a geom picked by some lane, covering
// nothing in the others) and the layers each pixel composites (every slot, with its coverage set
// to 0 in the lanes whose choice of `layers` leaves it out).
//
// The reverse pass (RenderVjp) draws each packet again and differentiates it backwards: by hand
// through the composite and the shading, and through each surface's geometry on forward-mode
// Dual numbers of packets (the same templates, with JAX's own derivative rules where
// primitives.py defines them: a search's result held constant, a cylinder's kinks). Forward
// mode stays with the JAX version (batching.py's custom JVP). Meshes are not drawn here (the
// Python side falls back to JAX).
//
// What it skips leaves the image as JAX draws it (renderer.negligible_coverage: a surface of
// coverage under the cut below decides nothing there): a ray that misses a geom's bounding
// sphere is not intersected with it; a surface is shaded only where it adds to the pixel (weight > 1e-12);
// a soft silhouette far from a pixel is not searched for: 30 tau pixels in float64 (coverage
// under 1e-13), 18 tau pixels in float32 (under 1.5e-8, a quarter of float32's resolution at 1).
// The hard image and shadow rays test every geom, where JAX culls crowded types to the nearest
// few (exact wherever those hold the first hit, resp. the occluder; culling only ever drops soft
// coverage). The reverse pass leaves out, besides, what adds under 1e-10 to a pixel: a surface
// whose coverage is under that, a distance where the coverage's sigmoid is that flat.
//
// Inputs: cam (..., 15) = pos (3), xmat (9, row-major; columns right, up, back), pixel size at
// unit depth, principal column and row; geo (..., G, 19) = xpos (3), xmat (9), size (3), albedo
// rgba (4), the renderer's geoms in its order; tg (..., 2) = the soft silhouette's temperature
// tau in pixels (0: the hard image) and the depth order's gamma. Outputs: rgb (..., H, W, 3),
// depth (..., H, W), segmentation and body ids (..., H, W) int32, weights (..., H, W, G),
// background (..., H, W). The reverse pass takes cam, geo, tg and the cotangents of rgb, depth,
// weights and background, and gives those of cam and geo.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
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

// ------------------------------------------------------------------ packets
// P<T>: one value per lane (GCC's vector extension: the compiler emits the CPU's SIMD
// instructions for the width it targets); Mask<T>: one truth value per lane. A packet converts
// from a number by broadcasting it, so the geometry templates read as scalar code does, with
// sel(mask, a, b) where scalar code would branch.
#if defined(__AVX512F__)
constexpr int kBytes = 64;
#elif defined(__AVX__)
constexpr int kBytes = 32;
#else
constexpr int kBytes = 16;
#endif

template <typename T> struct Ints;
template <> struct Ints<float> {
  using type = int32_t;
  static constexpr int mant = 23, bias = 127;
};
template <> struct Ints<double> {
  using type = int64_t;
  static constexpr int mant = 52, bias = 1023;
};

template <typename T>
struct Mask {
  using I = typename Ints<T>::type;
  typedef I VI __attribute__((vector_size(kBytes)));
  static constexpr int N = kBytes / sizeof(T);
  VI v;
  Mask() = default;
  explicit Mask(VI x) : v(x) {}
  Mask(bool b) : v(VI{} + I(b ? -1 : 0)) {}  // NOLINT: the scalar code's true / false
  friend Mask operator&(Mask a, Mask b) { return Mask(a.v & b.v); }
  friend Mask operator|(Mask a, Mask b) { return Mask(a.v | b.v); }
  friend Mask operator&&(Mask a, Mask b) { return Mask(a.v & b.v); }
  friend Mask operator||(Mask a, Mask b) { return Mask(a.v | b.v); }
  friend Mask operator!(Mask a) { return Mask(~a.v); }
  Mask& operator|=(Mask b) { v |= b.v; return *this; }
  Mask& operator&=(Mask b) { v &= b.v; return *this; }
  bool operator[](int l) const { return v[l] != 0; }
};

template <typename T> inline bool any(Mask<T> m) {
  typename Mask<T>::I r = 0;
  for (int l = 0; l < Mask<T>::N; ++l) r |= m.v[l];
  return r != 0;
}
template <typename T> inline bool all(Mask<T> m) {
  typename Mask<T>::I r = -1;
  for (int l = 0; l < Mask<T>::N; ++l) r &= m.v[l];
  return r != 0;
}
template <typename T> inline bool none(Mask<T> m) { return !any(m); }

template <typename T>
struct P {
  static constexpr int N = kBytes / sizeof(T);
  typedef T V __attribute__((vector_size(kBytes)));
  using M = Mask<T>;
  V v;
  P() = default;
  P(double x) : v(V{} + T(x)) {}  // NOLINT: constants broadcast
  explicit P(V x) : v(x) {}
  T operator[](int l) const { return v[l]; }
  friend P operator+(P a, P b) { return P(a.v + b.v); }
  friend P operator-(P a, P b) { return P(a.v - b.v); }
  friend P operator*(P a, P b) { return P(a.v * b.v); }
  friend P operator/(P a, P b) { return P(a.v / b.v); }
  friend P operator-(P a) { return P(-a.v); }
  P& operator+=(P b) { v += b.v; return *this; }
  P& operator-=(P b) { v -= b.v; return *this; }
  P& operator*=(P b) { v *= b.v; return *this; }
  P& operator/=(P b) { v /= b.v; return *this; }
  friend M operator<(P a, P b) { return M(a.v < b.v); }
  friend M operator>(P a, P b) { return M(a.v > b.v); }
  friend M operator<=(P a, P b) { return M(a.v <= b.v); }
  friend M operator>=(P a, P b) { return M(a.v >= b.v); }
  friend M operator==(P a, P b) { return M(a.v == b.v); }
  friend M operator!=(P a, P b) { return M(a.v != b.v); }
  friend P sel(M m, P a, P b) { return P(m.v ? a.v : b.v); }
};

// ------------------------------------------------------------------ forward-mode numbers
// Dual<T, N>: a value and its derivatives along N directions (T: a packet). The reverse kernel
// runs each surface's geometry (hit, closest approach, normal: the same templates the image
// uses) on these, seeded with the surface's 10 inputs, to get their Jacobian; the rest of a
// pixel (compositing, shading) is differentiated by hand. Ties of min / max / |x| split as JAX's
// derivatives do (half each; |x|' = 0 at 0), so that both give the same gradient.
template <typename T, int N>
struct Dual {
  using M = typename T::M;
  T v;
  T d[N];
  Dual() = default;
  Dual(double x) : v(T(x)) {  // NOLINT: constants mix freely
    for (int k = 0; k < N; ++k) d[k] = T(0);
  }
  explicit Dual(const T& x) : v(x) {  // a packet held constant
    for (int k = 0; k < N; ++k) d[k] = T(0);
  }
  static Dual seed(const T& x, int k) {
    Dual r(x);
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
  friend M operator<(const Dual& a, const Dual& b) { return a.v < b.v; }
  friend M operator>(const Dual& a, const Dual& b) { return a.v > b.v; }
  friend M operator<=(const Dual& a, const Dual& b) { return a.v <= b.v; }
  friend M operator>=(const Dual& a, const Dual& b) { return a.v >= b.v; }
  friend M operator==(const Dual& a, const Dual& b) { return a.v == b.v; }
  friend M operator!=(const Dual& a, const Dual& b) { return a.v != b.v; }
  friend Dual sel(M m, const Dual& a, const Dual& b) {
    Dual r;
    r.v = sel(m, a.v, b.v);
    for (int k = 0; k < N; ++k) r.d[k] = sel(m, a.d[k], b.d[k]);
    return r;
  }
};

template <typename T> struct IsDual { static constexpr bool value = false; };
template <typename T, int N> struct IsDual<Dual<T, N>> { static constexpr bool value = true; };

// a Dual's value (a packet as it is) and the same number held constant (stop_gradient)
template <typename T> inline P<T> value(const P<T>& x) { return x; }
template <typename T, int N> inline T value(const Dual<T, N>& x) { return x.v; }
template <typename T> inline P<T> constant(const P<T>& x) { return x; }
template <typename T, int N> inline Dual<T, N> constant(const Dual<T, N>& x) {
  return Dual<T, N>(x.v);
}
template <typename T> struct Base { using type = T; };
template <typename T, int N> struct Base<Dual<T, N>> { using type = T; };

template <typename T>
struct K {
  static T eps() { return T(1e-12); }
  static T inf() { return T(std::numeric_limits<double>::infinity()); }
};

// ------------------------------------------------------------------ packet arithmetic
template <typename T>
inline P<T> Sqrt(const P<T>& x) {
  P<T> r;
  for (int l = 0; l < P<T>::N; ++l) r.v[l] = std::sqrt(x.v[l]);
  return r;
}
template <typename T>
inline P<T> Fabs(const P<T>& x) {
  using VI = typename Mask<T>::VI;
  using I = typename Ints<T>::type;
  const I keep = ~(I(1) << (8 * sizeof(T) - 1));
  return P<T>((typename P<T>::V)((VI)x.v & keep));
}
template <typename T> inline Mask<T> Finite(const P<T>& x) { return (x - x) == P<T>(0.0); }
template <typename T> inline P<T> Min(const P<T>& a, const P<T>& b) { return sel(b < a, b, a); }
template <typename T> inline P<T> Max(const P<T>& a, const P<T>& b) { return sel(a < b, b, a); }

// exp: 2^n exp(r), |r| <= ln2 / 2 (Cody-Waite), Taylor to below the type's rounding, 2^n as two
// factors so that no intermediate leaves the normal range; overflow inf, underflow 0, NaN kept
template <typename T>
P<T> Exp(const P<T>& x) {
  using IT = Ints<T>;
  using VI = typename Mask<T>::VI;
  using V = typename P<T>::V;
  constexpr bool f32 = sizeof(T) == 4;
  const P<T> hi(f32 ? 88.72283935546875 : 709.782712893384);
  const P<T> lo(f32 ? -103.97208404541016 : -745.1332191019411);
  P<T> xc = Min(Max(x, lo), hi);
  const double magic = f32 ? 12582912.0 : 6755399441055744.0;  // 1.5 * 2^23, 1.5 * 2^52
  P<T> n = (xc * P<T>(1.4426950408889634) + P<T>(magic)) - P<T>(magic);
  P<T> r = xc - n * P<T>(f32 ? 0.693359375 : 6.93147180369123816490e-01);
  r = r - n * P<T>(f32 ? -2.12194440e-4 : 1.90821492927058770002e-10);
  const int deg = f32 ? 7 : 13;
  double cf[14];
  cf[0] = 1;
  for (int k = 1; k <= deg; ++k) cf[k] = cf[k - 1] / k;  // 1 / k!
  P<T> p(cf[deg]);
  for (int k = deg - 1; k >= 0; --k) p = P<T>(cf[k]) + r * p;
  VI ni = __builtin_convertvector(n.v, VI);
  VI n1 = ni >> 1, n2 = ni - n1;
  V s1 = (V)((n1 + typename IT::type(IT::bias)) << IT::mant);
  V s2 = (V)((n2 + typename IT::type(IT::bias)) << IT::mant);
  P<T> res = p * P<T>(s1) * P<T>(s2);
  res = sel(x > hi, K<P<T>>::inf(), res);
  res = sel(x < lo, P<T>(0.0), res);
  return sel(x != x, x, res);
}

// log: x = 2^e m, m in [sqrt(1/2), sqrt(2)); log(1 + f) = f - f^2/2 + s (f^2/2 + R) with
// s = f / (2 + f), R the series of 2 atanh(s) - 2 s over s (fdlibm's arrangement)
template <typename T>
P<T> Log(const P<T>& x) {
  using IT = Ints<T>;
  using I = typename IT::type;
  using VI = typename Mask<T>::VI;
  using V = typename P<T>::V;
  constexpr bool f32 = sizeof(T) == 4;
  const T tiny = std::numeric_limits<T>::min();
  auto small = x < P<T>(tiny);  // subnormal: scaled up by 2^mant first
  P<T> xs = sel(small, x * P<T>(std::ldexp(1.0, IT::mant)), x);
  VI bits = (VI)xs.v;
  VI e = ((bits >> IT::mant) & I((1 << (8 * sizeof(T) == 32 ? 8 : 11)) - 1)) - I(IT::bias);
  VI mb = (bits & ((I(1) << IT::mant) - 1)) | (I(IT::bias) << IT::mant);
  P<T> m((V)mb);
  auto big = m > P<T>(1.4142135623730951);
  m = sel(big, m * P<T>(0.5), m);
  P<T> ef(__builtin_convertvector(e, V));
  ef = ef + sel(big, P<T>(1.0), P<T>(0.0)) - sel(small, P<T>(double(IT::mant)), P<T>(0.0));
  P<T> f = m - P<T>(1.0);
  P<T> s = f / (P<T>(2.0) + f);
  P<T> z = s * s;
  const int terms = f32 ? 5 : 11;
  P<T> R(2.0 / (2 * terms + 1));
  for (int k = terms - 1; k >= 1; --k) R = P<T>(2.0 / (2 * k + 1)) + z * R;
  R = z * R;
  P<T> hfsq = P<T>(0.5) * f * f;
  P<T> res = ef * P<T>(f32 ? 0.693359375 : 6.93147180369123816490e-01) +
             (((f - hfsq) + s * (hfsq + R)) +
              ef * P<T>(f32 ? -2.12194440e-4 : 1.90821492927058770002e-10));
  res = sel(x == P<T>(0.0), -K<P<T>>::inf(), res);
  res = sel(x < P<T>(0.0), P<T>(std::numeric_limits<double>::quiet_NaN()), res);
  res = sel(x == K<P<T>>::inf(), x, res);
  return sel(x != x, x, res);
}

// f(x) with derivative f'(x) (the chain rule once, for the unary functions below)
template <typename T, int N>
inline Dual<T, N> chain(const Dual<T, N>& x, const T& f, const T& df) {
  Dual<T, N> r;
  r.v = f;
  for (int k = 0; k < N; ++k) r.d[k] = df * x.d[k];
  return r;
}

template <typename T, int N> inline Dual<T, N> Sqrt(const Dual<T, N>& x) {
  T s = Sqrt(x.v);
  return chain(x, s, T(0.5) / s);
}
template <typename T, int N> inline Dual<T, N> Exp(const Dual<T, N>& x) {
  T e = Exp(x.v);
  return chain(x, e, e);
}
template <typename T, int N> inline Dual<T, N> Log(const Dual<T, N>& x) {
  return chain(x, Log(x.v), T(1) / x.v);
}
template <typename T, int N> inline Dual<T, N> Fabs(const Dual<T, N>& x) {
  return chain(x, Fabs(x.v), sel(x.v > T(0), T(1), sel(x.v < T(0), T(-1), T(0))));
}
template <typename T, int N> inline typename T::M Finite(const Dual<T, N>& x) {
  return Finite(x.v);
}
template <typename T, int N>
inline Dual<T, N> Min(const Dual<T, N>& a, const Dual<T, N>& b) {
  return sel(a.v == b.v, (a + b) * Dual<T, N>(0.5), sel(b.v < a.v, b, a));
}
template <typename T, int N>
inline Dual<T, N> Max(const Dual<T, N>& a, const Dual<T, N>& b) {
  return sel(a.v == b.v, (a + b) * Dual<T, N>(0.5), sel(a.v < b.v, b, a));
}

template <typename T>
inline T dot3(const T* a, const T* b) { return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]; }

template <typename T>
inline T safe_div(T a, T b) {
  T e = K<T>::eps();
  return a / sel(Fabs(b) > e, b, sel(b < T(0), -e, e));
}

template <typename T>
inline T first_positive(T c) { return sel(c > T(0), c, K<T>::inf()); }

template <typename T>
inline T sigmoid(T x) { return T(1) / (T(1) + Exp(-x)); }

// p_loc = (v - xpos) @ xmat, or v @ xmat for directions (the matrix a packet's or a number's)
template <typename T, typename U>
inline void to_local(const T* v, const U* m, T* out) {
  for (int j = 0; j < 3; ++j)
    out[j] = (v[0] * T(m[j]) + v[1] * T(m[3 + j])) + v[2] * T(m[6 + j]);
}
template <typename T, typename U>
inline void to_world(const T* v, const U* m, T* out) {
  for (int i = 0; i < 3; ++i)
    out[i] = (v[0] * T(m[3 * i]) + v[1] * T(m[3 * i + 1])) + v[2] * T(m[3 * i + 2]);
}

// ------------------------------------------------------------------ first hits (local frame)
// Every function here runs on packets (T = P) and on Dual numbers of packets alike.

// the nearer of the line's two parameters at distance `rad` from the origin (n: 2 or 3 axes);
// the mask is false where it passes further away
template <typename T>
inline typename T::M line_root(const T* o, const T* r, int n, T rad, T& s0) {
  T A = n == 3 ? dot3(r, r) : r[0] * r[0] + r[1] * r[1];
  T B = n == 3 ? dot3(o, r) : o[0] * r[0] + o[1] * r[1];
  A = sel(A > K<T>::eps(), A, K<T>::eps());
  T f = B / A, ll = 0;
  for (int k = 0; k < n; ++k) {
    T lc = o[k] - f * r[k];
    ll = k == 0 ? lc * lc : ll + lc * lc;
  }
  T disc = A * (rad * rad - ll);
  T sq = sel(disc > T(0), Sqrt(disc), T(0));
  s0 = (-B - sq) / A;
  return disc >= T(0);
}

template <typename T>
inline T hit_sphere(const T* o, const T* r, T rad) {
  T s0;
  auto ok = line_root(o, r, 3, rad, s0);
  return sel(ok, first_positive(s0), K<T>::inf());
}

template <typename T>
inline T hit_tube(const T* o, const T* r, T rad, T h) {
  T s0;
  auto ok = line_root(o, r, 2, rad, s0);
  T z = o[2] + s0 * r[2];
  auto good = ok & (Fabs(z) <= h) & ((r[0] * r[0] + r[1] * r[1]) > K<T>::eps());
  return sel(good, first_positive(s0), K<T>::inf());
}

template <typename T>
T hit(int type, const T* o, const T* r, const T* sz) {
  const T inf = K<T>::inf();
  switch (type) {
    case 0: {  // plane z = 0, front side, finite rectangle where sizes > 0
      T s = safe_div(-o[2], r[2]);
      T px = o[0] + s * r[0], py = o[1] + s * r[1];
      auto in = (!(sz[0] > T(0)) | (Fabs(px) <= sz[0])) & (!(sz[1] > T(0)) | (Fabs(py) <= sz[1]));
      return sel((o[2] > T(0)) & (r[2] < T(0)) & in & (s > T(0)), s, inf);
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
        auto in = px * px + py * py <= rad * rad;
        caps = Min(caps, sel(in, first_positive(s), inf));
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
      return sel((tmin <= tmax) & (tmin > T(0)), tmin, inf);
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

// x[i] for a per-lane index i (a packet of small whole numbers) into 3 candidates
template <typename T, typename V>
inline T pick3(const V& i, const T* x) {
  return sel(i == V(0.0), x[0], sel(i == V(1.0), x[1], x[2]));
}

template <typename D>
void closest_cylinder_dual(const D* o, const D* r, const D* sz, int iters, D& s, D& d);

// the golden-section search of a cylinder's SDF along the ray (values only)
template <typename T>
void closest_cylinder(const T* o, const T* r, const T* sz, int iters, T& s, T& d) {
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
    auto left = fc < fd;
    hi = sel(left, dd, hi);
    lo = sel(left, lo, c);
    T nc = sel(left, hi - g * (hi - lo), dd);
    T nd = sel(left, c, lo + g * (hi - lo));
    T fx = f(sel(left, nc, nd));
    T fc2 = sel(left, fx, fd), fd2 = sel(left, fc, fx);
    fc = fc2, fd = fd2, c = nc, dd = nd;
  }
  s = T(0.5) * (lo + hi);
  d = f(s);
}

template <typename T>
void closest(int type, const T* o, const T* r, const T* sz, int iters, T& s, T& d) {
  const T inf = K<T>::inf();
  switch (type) {
    case 0: {
      T sp = safe_div(-o[2], r[2]);
      T px = o[0] + sp * r[0], py = o[1] + sp * r[1];
      auto front = (o[2] > T(0)) & (r[2] < T(0));
      T qx = Fabs(px) - sz[0], qy = Fabs(py) - sz[1];
      auto finite = (sz[0] > T(0)) & (sz[1] > T(0));
      T a = Max(qx, T(0)), b = Max(qy, T(0));
      T dd = Min(Max(qx, qy), T(0)) + Sqrt(a * a + b * b + T(1e-20));
      dd = sel(finite, dd, T(-1e3));
      s = sel(front, sp, inf);
      d = sel(front, dd, T(1e3));
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
      } else {
        closest_cylinder(o, r, sz, iters, s, d);
      }
      return;
    }
    case 6: {
      // inside: the deepest point (box_depth); outside: the nearest edge. The searches run on
      // values (V; on Dual numbers only the chosen piece is differentiated, as in JAX)
      using V = typename Base<T>::type;
      T A[3], Pp[3], Q[3];
      V Av[3], Pv[3], Qv[3], ov[3], rv[3], hv[3];
      for (int k = 0; k < 3; ++k) {
        T sg = sel(r[k] >= T(0), T(1), T(-1));
        A[k] = sg * r[k];
        Pp[k] = sg * o[k] - sz[k];
        Q[k] = -sg * o[k] - sz[k];
        Av[k] = value(A[k]), Pv[k] = value(Pp[k]), Qv[k] = value(Q[k]);
        ov[k] = value(o[k]), rv[k] = value(r[k]), hv[k] = value(sz[k]);
      }
      const V vinf = K<V>::inf();
      V best_v = 0, best_s = 0, bi = 0, bj = 0;
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
          V den = Av[i] + Av[j];
          auto ok = den > V(0);
          den = sel(ok, den, V(1));
          V v = sel(ok, (Av[i] * Qv[j] + Av[j] * Pv[i]) / den, -vinf);
          V sv = (Qv[j] - Pv[i]) / den;
          if (i == 0 && j == 0) {
            best_v = v, best_s = sv;
          } else {
            auto up = v > best_v;
            best_v = sel(up, v, best_v), best_s = sel(up, sv, best_s);
            bi = sel(up, V(double(i)), bi), bj = sel(up, V(double(j)), bj);
          }
        }
      T Ai = pick3(bi, A), Aj = pick3(bj, A), Pi = pick3(bi, Pp), Qj = pick3(bj, Q);
      T d_in = (Ai * Qj + Aj * Pi) / (Ai + Aj);
      auto inside = d_in < T(0);
      if (all(inside)) {
        s = T(best_s), d = d_in;  // s held constant, as JAX's box_depth
        return;
      }
      V rr = dot3(rv, rv), irr = V(1) / rr;
      V best_d = vinf;
      V ca[3] = {0, 0, 0}, ce[3] = {0, 0, 0};  // the nearest edge's corner and direction signs
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
        auto up = dd < best_d;
        best_d = sel(up, dd, best_d);
        for (int i = 0; i < 3; ++i)
          ca[i] = sel(up, V(kBox.a[k][i]), ca[i]), ce[i] = sel(up, V(kBox.e[k][i]), ce[i]);
      }
      T a[3], b[3];
      for (int i = 0; i < 3; ++i) {
        a[i] = T(ca[i]) * sz[i];
        b[i] = a[i] + T(ce[i]) * sz[i];
      }
      T s_e, d_e;
      line_segment(o, r, a, b, s_e, d_e);
      s = sel(inside, T(best_s), s_e);
      d = sel(inside, d_in, d_e);
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
    return sel(a > b, da, sel(b > a, db, (da + db) * U(0.5)));
  };
  U p[3] = {o[0] + t * r[0], o[1] + t * r[1], o[2] + t * r[2]};
  U rxy = Sqrt(p[0] * p[0] + p[1] * p[1] + U(1e-20));
  U q0 = rxy - sz[0], q1 = Fabs(p[2]) - sz[1];
  U dq0 = (p[0] * r[0] + p[1] * r[1]) / rxy;
  T pz = value(p[2]);
  U dq1 = sel(pz > T(0), r[2], sel(pz < T(0), -r[2], U(0)));
  T q0v = value(q0), q1v = value(q1), m = Max(q0v, q1v);
  U dm = pick(q0v, q1v, dq0, dq1);
  U dmn = sel(m < T(0), dm, sel(m > T(0), U(0), dm * U(0.5)));
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
  closest_cylinder(ov, rv, hv, iters, sv, dv);
  T rb = Sqrt(hv[0] * hv[0] + hv[1] * hv[1]);
  T rr = dot3(rv, rv);
  T sc = -dot3(ov, rv) / rr;
  T half = rb / Sqrt(rr) * T(1.05) + T(1e-6);
  T lo = Max(sc - half, T(1e-6)), hi = Max(sc + half, T(2e-6));
  T width = (hi - lo) * T(std::pow(0.6180339887498949, iters));
  D S(sv);
  D p[3];
  for (int k = 0; k < 3; ++k) p[k] = o[k] + S * r[k];
  T ps[3] = {value(p[0]), value(p[1]), value(p[2])};
  auto z_kink = Fabs(ps[2]) <= Fabs(rv[2]) * width;
  D rxy = Sqrt(p[0] * p[0] + p[1] * p[1] + D(1e-20));
  D q0 = rxy - sz[0];
  D q1 = sel(z_kink, constant(Fabs(p[2])), Fabs(p[2])) - sz[1];
  T d0 = (ps[0] * rv[0] + ps[1] * rv[1]) / value(rxy);
  T d1 = sel(z_kink, T(0), sel(ps[2] > T(0), rv[2], sel(ps[2] < T(0), -rv[2], T(0))));
  T q0s = value(q0), q1s = value(q1);
  auto inside = Max(q0s, q1s) < T(0);
  auto kink = (d0 * d1 < T(0)) & (Fabs(q0s - q1s) <= (Fabs(d0) + Fabs(d1)) * width);
  T lam = safe_div(d1, d1 - d0);
  D g = sel(kink, D(lam) * q0 + D(T(1) - lam) * q1, sel(q1s > q0s, q1, q0));
  D dd = sdf_cylinder(p, sz[0], sz[1]);
  // f'' along the ray at s (a constant): the slope's own derivative in s
  using D1 = Dual<T, 1>;
  D1 o1[3], r1[3], h1[3];
  for (int k = 0; k < 3; ++k) o1[k] = D1(ov[k]), r1[k] = D1(rv[k]), h1[k] = D1(hv[k]);
  T curve = cylinder_slope(D1::seed(sv, 0), o1, r1, h1).d[0];
  auto curved = curve > K<T>::eps();
  D step = -cylinder_slope(S, o, r, sz) / D(sel(curved, curve, T(1)));
  s_out = sel(!inside & curved, S + step - constant(step), S);
  d_out = sel(inside, constant(dd) + g - constant(g), dd);
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
      T w_cap = soft ? sigmoid((dr - dz) / tn) : sel(dz < dr, T(1), T(0));
      T side = (T(1) - w_cap) / rxy;
      n[0] = side * p[0], n[1] = side * p[1], n[2] = w_cap * sel(p[2] >= T(0), T(1), T(-1));
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
        auto k0 = (d[0] <= d[1]) & (d[0] <= d[2]);
        auto k1 = !k0 & (d[1] <= d[2]);
        w[0] = sel(k0, T(1), T(0)), w[1] = sel(k1, T(1), T(0));
        w[2] = sel(!k0 & !k1, T(1), T(0));
      }
      for (int k = 0; k < 3; ++k) n[k] = w[k] * sel(p[k] >= T(0), T(1), T(-1));
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
    case 6: return std::sqrt((sz[0] * sz[0] + sz[1] * sz[1]) + sz[2] * sz[2]);
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
inline typename T::M far_from(int t, const T* o, const T* r, T rb, T gap, T px, T near_,
                              T margin) {
  if (t == 0 || t == 4) return false;
  T rr = dot3(r, r);
  T s_max = -dot3(o, r) / rr + rb / Sqrt(rr) * T(1.05) + T(1e-6);
  return (gap > T(0)) & (gap > margin * Max(s_max, near_) * px);
}

// lax.top_k's indices, per lane: the k largest of x[0..n), largest first, ties to the lower
// index (out: packets of indices)
template <typename T>
inline void top_k(const T* x, int n, int k, T* out) {
  using M = typename T::M;
  M taken[64];
  for (int j = 0; j < n; ++j) taken[j] = false;
  for (int q = 0; q < k; ++q) {
    T best = 0, bidx = -1;
    for (int j = 0; j < n; ++j) {
      M take = !taken[j] & ((bidx < T(0)) | (x[j] > best));
      best = sel(take, x[j], best);
      bidx = sel(take, T(double(j)), bidx);
    }
    out[q] = bidx;
    for (int j = 0; j < n; ++j) taken[j] |= bidx == T(double(j));
  }
}

// ------------------------------------------------------------------ packets of pixels
// A packet's lane l is the pixel (i0 + l / tile_w, j0 + l % tile_w): a tile of tile_w columns
template <typename T> constexpr int tile_w() { return P<T>::N >= 4 ? 4 : P<T>::N; }
template <typename T> constexpr int tile_h() { return P<T>::N / tile_w<T>(); }

template <typename T>
inline P<T> lane_column() {
  P<T> r;
  for (int l = 0; l < P<T>::N; ++l) r.v[l] = T(l % tile_w<T>());
  return r;
}
template <typename T>
inline P<T> lane_row() {
  P<T> r;
  for (int l = 0; l < P<T>::N; ++l) r.v[l] = T(l / tile_w<T>());
  return r;
}

// arr[stride * idx[l] + comp][l] in lane l: a per-slot packet array read at each lane's own slot
template <typename T>
inline P<T> pick_lanes(const P<T>* arr, int stride, const P<T>& idx, int comp) {
  P<T> r;
  for (int l = 0; l < P<T>::N; ++l) r.v[l] = arr[stride * int(idx[l]) + comp][l];
  return r;
}

template <typename T>
inline T hsum(const P<T>& x) {
  T s = 0;
  for (int l = 0; l < P<T>::N; ++l) s += x[l];
  return s;
}

template <typename T, typename U>
inline T dot3m(const T* a, const U* b) {
  return (a[0] * T(b[0]) + a[1] * T(b[1])) + a[2] * T(b[2]);
}

// ------------------------------------------------------------------ the scene
struct Config {
  ffi::Span<const int32_t> types, gids, bodies, opts;
  ffi::Span<const double> mat, lights, headlight, scal;
};

// One light's part in a surface's shading, kept from shade_vjp's colour for its reverse: the
// direction, factor (shadow included) and, for point and spot lights, distance, attenuation and
// falloff; the Blinn-Phong terms
template <typename T>
struct LightTerms {
  P<T> l[3], factor, dist, f0, spot;
  P<T> ndl, h[3], hn, ndh, nh, sp, nd;
  const T *amb, *dif, *spe;
  int kind;  // 0 headlight, 1 directional, 2 point or spot
  int index;
};

template <typename T>
struct Scratch;

template <typename T>
struct Scene {
  using Pk = P<T>;
  using Mk = Mask<T>;
  int G, NL;
  int iters, per_pixel, cull_above, layers;
  bool shadows;
  T near_, far_, far_depth, tau, gamma;
  T margin;  // far_from's cut, in tau pixels (see the header)
  T negligible;  // sigmoid(-margin): renderer.negligible_coverage
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
    margin = sizeof(T) == 4 ? T(18) : T(30);
    negligible = sizeof(T) == 4 ? T(1.5229979744712629e-08) : T(9.357622968840175e-14);
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

  // The capsule culling bounds each geom of a crowded type by: a segment along its longest
  // axis (half its half-length) and a radius (cast.choose)
  static void capsule(int t, const T* h, T& half, T& rad, int& col) {
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
  }

  // cast.choose: each lane's per_pixel best geoms among the candidates `cand` (renderer
  // indices, in their group's order: the geoms of one crowded type that a block's rays pass
  // near), as positions in cand (out; m = min(per_pixel, candidates) of them), and whether each
  // pick is near the lane's ray (near: through its capsule or within the soft band): a pick
  // that is not only fills a place and covers nothing
  int choose(int t, const int* cand, int n, const T* geo, const Pk* o, const Pk* r, T reach,
             T front, Pk* out, Mk* near, Pk* score) const {
    for (int j = 0; j < n; ++j) {
      const T* gp = geo + 19 * cand[j];
      const T* c = gp;
      const T* m = gp + 3;
      T half, rad;
      int col;
      capsule(t, gp + 12, half, rad, col);
      Pk a[3], b[3];
      for (int i = 0; i < 3; ++i) {
        T e = half * m[3 * i + col];
        a[i] = Pk(c[i] - e), b[i] = Pk(c[i] + e);
      }
      Pk s_c, dist;
      line_segment(o, r, a, b, s_c, dist);
      Pk depth = Max(s_c, Pk(near_));
      Pk lim = Pk(rad) + Pk(reach) * depth;
      Mk ahead = s_c + Pk(half) + Pk(rad) >= Pk(front);
      Mk core = dist <= Pk(rad * T(1.001) + T(1e-6));
      Mk band = (dist <= lim * Pk(1.001) + Pk(1e-6)) & ahead;
      score[j] = sel(core & ahead, Pk(1e6) - s_c,
                     sel(band, -(dist - Pk(rad)) / depth, Pk(-1e9) - dist));
    }
    int m = std::min(per_pixel, n);
    top_k(score, n, m, out);
    for (int q = 0; q < m; ++q) near[q] = pick_lanes(score, 1, out[q], 0) > Pk(-1e8);
    return m;
  }

  // the direction l towards light i from p and its distance; where asked, its factor: the
  // attenuation f0 times the spot's falloff (shadows need the direction alone)
  void light_dir(int i, const Pk* p, Pk* l, Pk& dist, Pk* factor, Pk* f0 = nullptr,
                 Pk* spot = nullptr) const {
    const T* L = &light[i * kLightStride];
    int type = int(L[0]);
    if (type == 1) {
      for (int k = 0; k < 3; ++k) l[k] = Pk(-L[4 + k]);
      dist = Pk(1e9);
      if (factor) *factor = Pk(1);
      return;
    }
    Pk dl[3];
    for (int k = 0; k < 3; ++k) dl[k] = Pk(L[1 + k]) - p[k];
    dist = Sqrt(dot3(dl, dl) + Pk(1e-20));
    for (int k = 0; k < 3; ++k) l[k] = dl[k] / dist;
    if (!factor) return;
    Pk att = Pk(1) / (Pk(L[18]) + Pk(L[19]) * dist + Pk(L[20]) * dist * dist), fall = 1;
    if (type == 0) {
      Pk cosang = -dot3m(l, L + 4);
      Mk inside = cosang >= Pk(cutoff_cos[i]);
      fall = any(inside) ? sel(inside, Exp(Pk(L[17]) * Log(Max(cosang, Pk(1e-30)))), Pk(0))
                         : Pk(0);
    }
    *factor = type == 0 ? att * fall : att;
    if (f0) *f0 = att;
    if (spot) *spot = fall;
  }

  // shading.unoccluded: 1 where the ray from p to the light meets no geom but the lane's
  // `skip`. Every geom is tested (bounding spheres first; rb: the frame's bounding radii), where
  // JAX tests a culled type's `per_pixel` nearest: the same verdict wherever those include the
  // occluder.
  // A geom first meets a packet-level bound: every lane's shadow ray lies within rho (+ its 1e-5
  // offsets) of the segment from the lanes' mean point m towards light li (to the light's
  // position, or along a directional light), so a bounding sphere further from that segment
  // blocks no lane.
  Pk unoccluded(const T* geo, const T* rb, const Pk* p, const Pk* l, const Pk& dist,
                const Pk& skip, int li) const {
    Pk o[3];
    for (int k = 0; k < 3; ++k) o[k] = p[k] + Pk(1e-5) * l[k];
    double m[3], rho = 0;
    for (int k = 0; k < 3; ++k) m[k] = double(hsum(p[k])) / Pk::N;
    for (int q = 0; q < Pk::N; ++q) {
      double d2 = 0;
      for (int k = 0; k < 3; ++k) d2 += (double(p[k][q]) - m[k]) * (double(p[k][q]) - m[k]);
      rho = std::max(rho, std::sqrt(d2));
    }
    const T* L = &light[li * kLightStride];
    const bool directional = int(L[0]) == 1;
    double e[3], len = 0;  // the segment's direction (unit) and length
    for (int k = 0; k < 3; ++k) e[k] = directional ? -double(L[4 + k]) : double(L[1 + k]) - m[k];
    for (int k = 0; k < 3; ++k) len += e[k] * e[k];
    len = std::sqrt(len);
    for (int k = 0; k < 3; ++k) e[k] = len > 0 ? e[k] / len : 0;
    if (directional) len = 1e300;
    // the bound for every geom at once (a packet of geoms; `centres`: the frame's per geom)
    using Pd = P<double>;
    uint64_t close = 0;  // a bit a geom (G <= 64)
    for (int g0 = 0; g0 < G; g0 += Pd::N) {
      Pd along = 0, d2 = 0, c[3];
      for (int k = 0; k < 3; ++k) {
        for (int q = 0; q < Pd::N; ++q)
          c[k].v[q] = g0 + q < G ? double(geo[19 * (g0 + q) + k]) - m[k] : 1e300;
        along += c[k] * Pd(e[k]);
      }
      along = Min(Max(along, Pd(0.0)), Pd(len));
      for (int k = 0; k < 3; ++k) d2 += (c[k] - along * Pd(e[k])) * (c[k] - along * Pd(e[k]));
      for (int q = 0; q < Pd::N && g0 + q < G; ++q) {
        double reach = double(rb[g0 + q]) * 1.001 + 1e-6 + rho + 3e-5;
        if (d2[q] <= reach * reach * (1 + 1e-6) + 1e-12) close |= uint64_t(1) << (g0 + q);
      }
    }
    Mk blocked = false;
    for (int g = 0; g < G; ++g) {
      int t = types[g];
      if (t == 0) continue;  // a plane casts no shadow upwards
      if (!((close >> g) & 1)) continue;
      const T* gp = geo + 19 * g;
      Pk d[3], ol[3], rl[3];
      for (int k = 0; k < 3; ++k) d[k] = o[k] - Pk(gp[k]);
      to_local(d, gp + 3, ol);
      to_local(l, gp + 3, rl);
      Mk cand = !blocked & (skip != Pk(double(g))) & !(bound_gap(ol, rl, Pk(rb[g])) > Pk(0));
      if (none(cand)) continue;
      Pk sz[3] = {Pk(gp[12]), Pk(gp[13]), Pk(gp[14])};
      blocked |= cand & (hit(t, ol, rl, sz) < dist);
      if (all(blocked)) break;
    }
    return sel(blocked, Pk(0), Pk(1));
  }

  void shade(const Pk* p, const Pk* n, const T* o, const T* fwd, const Pk* alb, const Pk* mat,
             const Pk* lit, Pk* col) const {
    Pk v[3];
    for (int k = 0; k < 3; ++k) v[k] = Pk(o[k]) - p[k];
    Pk vn = Sqrt(dot3(v, v) + Pk(1e-20));
    for (int k = 0; k < 3; ++k) v[k] /= vn;
    Pk spec_m = mat[0], sh = Pk(128) * mat[1];
    for (int k = 0; k < 3; ++k) col[k] = mat[2] * alb[k];
    auto add = [&](const Pk* l, const T* amb, const T* dif, const T* spe, const Pk& factor) {
      Pk ndl = dot3(n, l);
      Pk h[3] = {l[0] + v[0], l[1] + v[1], l[2] + v[2]};
      Pk hn = Sqrt(dot3(h, h) + Pk(1e-20));
      for (int k = 0; k < 3; ++k) h[k] /= hn;
      Pk ndh = Max(dot3(n, h), Pk(0));
      Mk lit_side = ndl > Pk(0);
      Pk sp = any(lit_side) ? sel(lit_side, Exp(sh * Log(ndh + Pk(1e-30))), Pk(0)) : Pk(0);
      Pk nd = Max(ndl, Pk(0));
      for (int k = 0; k < 3; ++k)
        col[k] = col[k] + Pk(amb[k]) * alb[k] +
                 factor * (Pk(dif[k]) * nd * alb[k] + Pk(spe[k]) * spec_m * sp);
    };
    if (head_on) {
      Pk l[3] = {Pk(-fwd[0]), Pk(-fwd[1]), Pk(-fwd[2])};
      add(l, head, head + 3, head + 6, Pk(1));
    }
    for (int i = 0; i < NL; ++i) {
      const T* L = &light[i * kLightStride];
      Pk l[3], dist, factor;
      light_dir(i, p, l, dist, &factor);
      if (shadows && L[21] != 0) factor = factor * lit[i];
      add(l, L + 7, L + 10, L + 13, factor);
    }
    for (int k = 0; k < 3; ++k) col[k] = Min(Max(col[k], Pk(0)), Pk(1));
  }
};

// A packet's rays and what they meet, up to the surfaces they composite.
template <typename T>
struct Ray {
  P<T> r[3], jj, ii;  // direction; each lane's pixel column and row
  T fwd[3], px;
  int S;            // surface slots, each composited as a layer (in slot order)
  bool any_dropped;  // some lane leaves some slot out of its composite (Scratch::kept)
  P<T> first, first_hit;  // the slot of the first hit, its depth
  Mask<T> any_hit;
};

// per-thread scratch: per surface slot (a soft image has at most Scene::slots surfaces a pixel,
// a hard one every geom) and per composited layer
template <typename T>
struct Scratch {
  using Pk = P<T>;
  using Mk = Mask<T>;
  // per slot: its primitive type and geom
  std::vector<int> type, gid;
  // per slot: first hit, depth where it is placed, signed distance, coverage, depth used,
  // the camera and ray in the geom's frame, world point, point in the geom's frame (for its
  // normal, found only where it is shaded), albedo
  std::vector<Pk> s_hit, s_n, dist, cover, z, key;
  std::vector<Pk> ol, rl, p, pl, alb;
  // per slot: the ray misses the bounding sphere; far from the silhouette too, or (culled) the
  // pick is not near it: coverage 0 there, nothing searched or differentiated
  std::vector<Mk> miss, far;
  // per layer: the lanes that composite it (where some lane leaves it out); the composite's
  // inputs and weights
  std::vector<Mk> kept;
  std::vector<Pk> a, zz, alpha, w, wa, wrgb;
  Pk bg, bg_rgb;
  std::vector<Pk> ahead, occl, dahead;  // layer pairs
  std::vector<Pk> score, pick, lit;
  std::vector<LightTerms<T>> lights;  // shade_vjp's, NL + 1
  // the reverse pass's cotangents, per layer and per slot
  std::vector<Pk> d_w, d_zz, d_a, d_wa, d_wrgb;
  std::vector<Pk> d_hit, d_sn, d_dist, d_z, d_nl;
  std::vector<Mk> shaded;
  // per geom, per frame: the camera in its frame, that point's squared distance from the
  // centre, the bounding radius
  std::vector<T> fol, foo, frb;
  // per geom, per packet (gather's first pass): the rays in its frame, their miss and far
  // masks, where a far ray is placed
  std::vector<Pk> grl, gsnf;
  std::vector<Mk> gmiss, gfar;
  // per block of kBlock x kBlock pixels of this frame's current row of blocks (block_geoms):
  // the geoms its rays can need, per block column (a list; done: computed)
  int64_t blk_frame = -1;
  int blk_row = -1;
  std::vector<std::vector<int>> blk;
  std::vector<char> blk_done;
  std::vector<char> need;  // per geom: in the current packet's block's list
  std::vector<int> cand;
  // the reverse pass's gradients of this worker's current frame, lane by lane
  std::vector<Pk> gcam, ggeo;
  int64_t frame = -1, acc_frame = -1;
  Scratch(int slots, int G, int NL) {
    // slots: a packet's are at most one a geom (a crowded type's picks too)
    const size_t S = std::max(std::max(slots, G), 1);
    type.resize(S), gid.resize(S);
    for (auto* v : {&s_hit, &s_n, &dist, &cover, &z, &key, &d_hit, &d_sn, &d_dist, &d_z})
      v->resize(S);
    for (auto* v : {&ol, &rl, &p, &pl, &d_nl}) v->resize(3 * S);
    alb.resize(4 * S);
    miss.resize(S), far.resize(S), shaded.resize(S);
    grl.resize(3 * size_t(G)), gsnf.resize(G), gmiss.resize(G), gfar.resize(G);
    need.resize(G), cand.resize(G);
    for (auto* v : {&a, &zz, &alpha, &w, &wa, &wrgb, &d_w, &d_zz, &d_a, &d_wa, &d_wrgb})
      v->resize(S);
    kept.resize(S);
    for (auto* v : {&ahead, &occl, &dahead}) v->resize(S * S);
    score.resize(std::max(S, size_t(64))), pick.resize(64), lit.resize(std::max(NL, 1));
    lights.resize(NL + 1);
    fol.resize(3 * G), foo.resize(G), frb.resize(G);
    gcam.assign(15, Pk(0)), ggeo.assign(19 * size_t(G), Pk(0));
  }
  // field f of slot s's geom (geo: the frame's (G, 19) rows)
  Pk param(const T* geo, int s, int f) const { return Pk(geo[19 * gid[s] + f]); }
  // slot s's material (specular, shininess, emission)
  void material(const Scene<T>& sc, int s, Pk* mat) const {
    mat[0] = Pk(sc.spec[gid[s]]), mat[1] = Pk(sc.shin[gid[s]]), mat[2] = Pk(sc.emis[gid[s]]);
  }
  // the reverse pass: v added to field f of slot s's geom's gradient, lane by lane
  void add_geom(int s, int f, const Pk& v) { ggeo[19 * gid[s] + f] += v; }
};

// ahead[g * S + k]: how much surface k lies in front of surface g (soft: a sigmoid of their depth
// difference over gamma; hard: 0 or 1); only between two surfaces that both cover the pixel in
// some lane, the only pairs `composite` reads, unless every_pair (the reverse pass's
// composite_vjp reads them all)
template <typename T>
void depth_order(int S, const P<T>* a, const P<T>* z, bool soft, T gamma, P<T>* ahead,
                 bool every_pair = false) {
  using Pk = P<T>;
  for (int g = 0; g < S; ++g)
    for (int k = g + 1; k < S; ++k) {
      if (!every_pair && none((a[g] != Pk(0)) & (a[k] != Pk(0)))) continue;
      if (soft) {
        Pk e = Exp((z[k] - z[g]) / Pk(gamma));  // sigmoid((z_g - z_k) / gamma) = 1 / (1 + e)
        ahead[g * S + k] = Pk(1) / (Pk(1) + e);
        ahead[k * S + g] = Pk(1) / (Pk(1) + Pk(1) / e);
      } else {
        ahead[g * S + k] = sel(z[k] < z[g], Pk(1), Pk(0));
        ahead[k * S + g] = sel(z[g] < z[k], Pk(1), Pk(0));
      }
    }
}

// w_g = a_g prod_{k != g} (1 - a_k ahead[g, k]), background prod_k (1 - a_k), both normalised
template <typename T>
void composite(int S, const P<T>* a, const P<T>* ahead, P<T>* w, P<T>& bg) {
  using Pk = P<T>;
  Pk tot = 0;
  bg = 1;
  for (int k = 0; k < S; ++k) bg = k == 0 ? Pk(1) - a[0] : bg * (Pk(1) - a[k]);
  for (int g = 0; g < S; ++g) {
    Pk prod = 1;
    auto ag = a[g] != Pk(0);
    for (int k = 0; k < S; ++k) {
      Pk occl = 1;
      if (k != g) occl = sel((a[k] != Pk(0)) & ag, Pk(1) - a[k] * ahead[g * S + k], Pk(1));
      prod = k == 0 ? occl : prod * occl;
    }
    w[g] = a[g] * prod;
    tot = g == 0 ? w[0] : tot + w[g];
  }
  tot = tot + bg;
  tot = sel(tot > Pk(0), tot, Pk(1));
  for (int g = 0; g < S; ++g) w[g] = w[g] / tot;
  bg = bg / tot;
}

constexpr int kBlock = 16;  // pixels a side of the blocks whose rays block_geoms bounds

// The geoms a block of pixels (rows i0..i1, columns j0..j1, inclusive) can need: the cone of its
// rays' lines (the block's central ray and the widest angle to a corner's) against each geom's
// bounding sphere. Left out is a geom that, for every ray of the block, the hard image misses;
// the soft image passes far from (far_from; ellipsoids and planes are always in); or, in a
// crowded type culling picks from, passes beyond culling's band (such a pick covers nothing).
// Conservative (double precision, margins for the float32 tests it stands for): a geom left out
// would have been a dead slot in every lane, whose coverage is negligible (the header).
template <typename T>
void block_geoms(const Scene<T>& sc, const T* cam, const T* geo, const Scratch<T>& X, int i0,
                 int i1, int j0, int j1, std::vector<int>& out) {
  const bool soft = sc.tau != 0;
  const double px = cam[12], cx = cam[13], cy = cam[14];
  auto dir = [&](double i, double j, double* u) {
    double loc[3] = {(j + 0.5 - cx) * px, (cy - i - 0.5) * px, -1.0}, n = 0;
    for (int k = 0; k < 3; ++k) {
      u[k] = loc[0] * cam[3 + 3 * k] + loc[1] * cam[4 + 3 * k] + loc[2] * cam[5 + 3 * k];
      n += u[k] * u[k];
    }
    for (int k = 0; k < 3; ++k) u[k] /= std::sqrt(n);
  };
  double dc[3], cos_t = 1;
  dir(0.5 * (i0 + i1), 0.5 * (j0 + j1), dc);
  for (int c = 0; c < 4; ++c) {
    double u[3];
    dir(c & 1 ? i1 : i0, c & 2 ? j1 : j0, u);
    cos_t = std::min(cos_t, dc[0] * u[0] + dc[1] * u[1] + dc[2] * u[2]);
  }
  cos_t = std::max(-1.0, cos_t - 1e-9);
  const double sin_t = std::sqrt(std::max(0.0, 1 - cos_t * cos_t));
  const double reach = (soft ? 15 * double(sc.tau) + 2 : 2) * px;
  out.clear();
  for (const auto& grp : sc.groups) {
    const int t = grp.first;
    const bool cull = soft && sc.culled(t, int(grp.second.size()));
    for (int g : grp.second) {
      const T* gp = geo + 19 * g;
      if (t == 0 || (soft && t == 4 && !cull)) {
        out.push_back(g);
        continue;
      }
      double c[3], D = 0, ca = 0;
      for (int k = 0; k < 3; ++k) c[k] = double(gp[k]) - double(cam[k]), D += c[k] * c[k];
      D = std::sqrt(D);
      for (int k = 0; k < 3; ++k) ca += c[k] * dc[k];
      ca = D > 0 ? std::fabs(ca) / D : 1;  // the angle of the centre off the lines' axis
      // the centre's least distance from the block's ray lines
      double perp = ca >= cos_t ? 0 : D * (std::sqrt(std::max(0.0, 1 - ca * ca)) * cos_t -
                                           ca * sin_t);
      perp = std::max(0.0, perp) * (1 - 1e-3) - 1e-7;
      const double rb = X.frb[g];
      bool needed;
      if (!soft) {
        needed = perp <= rb * 1.001 + 1e-6;
      } else if (!cull) {
        double thr = double(sc.margin) * double(sc.tau) * px *
                     std::max(D + 1.05 * rb + 1e-6, double(sc.near_));
        needed = !(perp - rb * 1.001 - 1e-6 > thr * (1 + 1e-3));
      } else {
        T half, rad;
        int col;
        Scene<T>::capsule(t, gp + 12, half, rad, col);
        double lim = double(rad) + reach * std::max(D + double(half), double(sc.near_));
        needed = perp - double(half) <= (lim * 1.001 + 1e-6) * (1 + 1e-3);
      }
      if (needed) out.push_back(g);
    }
  }
}

template <typename T>
void gather(const Scene<T>& sc, const T* cam, const T* geo, int i0, int j0, int64_t H,
            int64_t W, int64_t b, Scratch<T>& X, Ray<T>& R) {
  // X.fol / X.foo / X.frb: the camera in each geom's frame, its squared distance from the
  // geom's centre and the geom's bounding radius (per frame: begin_frame)
  using Pk = P<T>;
  using Mk = Mask<T>;
  const bool soft = sc.tau != 0;
  const T* cm = cam + 3;
  T px = cam[12], cx = cam[13], cy = cam[14];
  R.jj = Pk(double(j0)) + lane_column<T>();
  R.ii = Pk(double(i0)) + lane_row<T>();
  Pk loc[3] = {(R.jj + Pk(0.5) - Pk(cx)) * Pk(px), (Pk(cy) - R.ii - Pk(0.5)) * Pk(px), Pk(-1)};
  Pk* r = R.r;
  for (int k = 0; k < 3; ++k)
    r[k] = (loc[0] * Pk(cm[3 * k]) + loc[1] * Pk(cm[3 * k + 1])) + loc[2] * Pk(cm[3 * k + 2]);
  for (int k = 0; k < 3; ++k) R.fwd[k] = -cm[3 * k + 2];
  R.px = px;
  T band = soft ? T(15) * sc.tau + T(2) : T(2);
  T reach = band * px;
  Pk O[3] = {Pk(cam[0]), Pk(cam[1]), Pk(cam[2])};
  const Pk inf = K<Pk>::inf();

  // the geoms this packet's block can need (cached per block)
  const int bi = i0 / kBlock, bj = j0 / kBlock;
  if (X.blk_frame != b || X.blk_row != bi) {
    X.blk_frame = b, X.blk_row = bi;
    X.blk.resize((W + kBlock - 1) / kBlock);
    X.blk_done.assign(X.blk.size(), 0);
  }
  if (!X.blk_done[bj]) {
    block_geoms(sc, cam, geo, X, bi * kBlock, int(std::min<int64_t>(H, (bi + 1) * kBlock)) - 1,
                bj * kBlock, int(std::min<int64_t>(W, (bj + 1) * kBlock)) - 1, X.blk[bj]);
    X.blk_done[bj] = 1;
  }
  const std::vector<int>& needed = X.blk[bj];
  std::fill(X.need.begin(), X.need.end(), 0);

  // Every needed geom against the packet's rays, once: the rays in its frame, whether each
  // misses its bounding sphere, whether it passes so far from the silhouette that the geom's
  // coverage is negligible (the header; nothing is searched for there), where such a ray is
  // placed; whether any lane needs the geom (hard image: a ray that may hit it; soft: one not
  // far from it).
  for (int g : needed) {
    int t = sc.types[g];
    const T* gp = geo + 19 * g;
    Pk* rl = &X.grl[3 * g];
    to_local(r, gp + 3, rl);
    if (t == 0) {
      X.gmiss[g] = false, X.gfar[g] = false, X.need[g] = 1;
      continue;
    }
    const T* olv = &X.fol[3 * g];
    Pk ol[3] = {Pk(olv[0]), Pk(olv[1]), Pk(olv[2])};
    Pk rr = dot3(rl, rl), orr = dot3(ol, rl);
    Pk rb = X.frb[g], rbm = rb * Pk(1.001) + Pk(1e-6);
    Mk mm = Pk(X.foo[g]) * rr - orr * orr - rbm * rbm * rr > Pk(0);  // (squared, no root)
    Pk gap = -1;
    if (any(mm)) gap = sel(mm, soft ? bound_gap(ol, rl, rb) : Pk(1), Pk(-1));
    Mk miss = gap > Pk(0), farm = false;
    if (soft)
      farm = far_from(t, ol, rl, rb, gap, Pk(px), Pk(sc.near_), Pk(sc.margin * sc.tau));
    X.gmiss[g] = miss, X.gfar[g] = farm;
    X.need[g] = soft ? !all(farm) : !all(miss);
    if (soft) {
      Pk snf = -orr / rr;
      X.gsnf[g] = sel(Finite(snf), snf, Pk(sc.far_));
    }
  }

  // The surface slots some lane needs, in render_jax's order of groups: a slot no lane
  // needs adds nothing to the image and is left out.
  int S = 0;
  for (const auto& grp : sc.groups) {
    int t = grp.first;
    const auto& idx = grp.second;
    int n = int(idx.size());
    // Culling only ever drops coverage from the soft image: the hard image tests every geom
    // (bounding spheres first), which is what culling keeps it equal to.
    bool cull = soft && sc.culled(t, n);
    // culled: each geom some lane picks, near its ray, is a slot of its own, covering nothing
    // in the other lanes (as the pick it is not there)
    int m = n;
    const int* geoms = idx.data();
    Mk picked[64];
    if (cull) {
      int nc = 0;  // the block's candidates (every lane's near geoms are among them)
      for (int g : needed)
        if (sc.types[g] == t) X.cand[nc++] = g;
      Mk near[64];
      int k = nc ? sc.choose(t, X.cand.data(), nc, geo, O, r, reach, sc.near_, X.pick.data(),
                             near, X.score.data())
                 : 0;
      for (int j = 0; j < nc; ++j) picked[j] = false;
      for (int q = 0; q < k; ++q)
        for (int j = 0; j < nc; ++j) picked[j] |= near[q] & (X.pick[q] == Pk(double(j)));
      m = nc, geoms = X.cand.data();
    }
    for (int q = 0; q < m; ++q) {
      const int g = geoms[q];
      Mk farm;
      if (cull) {
        if (none(picked[q])) continue;
        farm = X.gfar[g] | !picked[q];
        if (all(farm)) continue;
      } else {
        if (!X.need[g]) continue;
        farm = X.gfar[g];
      }
      X.type[S] = t;
      X.gid[S] = g;
      Pk* ol = &X.ol[3 * S];
      Pk* rl = &X.rl[3 * S];
      for (int k = 0; k < 3; ++k) ol[k] = Pk(X.fol[3 * g + k]), rl[k] = X.grl[3 * g + k];
      X.miss[S] = X.gmiss[g] | (cull ? !picked[q] : Mk(false));
      X.far[S] = farm;
      Pk sz[3];
      for (int k = 0; k < 3; ++k) sz[k] = X.param(geo, S, 12 + k);
      const Mk miss = X.miss[S];
      Pk s_hit = all(miss) ? inf : sel(miss, inf, hit(t, ol, rl, sz));
      Pk sn, dist = 0;
      if (!soft) {
        sn = s_hit;
      } else {
        Pk s_c;
        closest(t, ol, rl, sz, sc.iters, s_c, dist);
        sn = sel(Finite(s_hit), s_hit, s_c);
        sn = sel(Finite(sn), sn, Pk(sc.far_));
        if (any(farm)) sn = sel(farm, X.gsnf[g], sn), dist = sel(farm, inf, dist);
      }
      // the normal is found only where the surface is shaded (draw_packet's shading loop)
      Pk sp = soft ? sn : sel(Finite(s_hit), s_hit, Pk(sc.far_));
      for (int k = 0; k < 3; ++k) X.pl[3 * S + k] = ol[k] + sp * rl[k];
      X.s_hit[S] = sel((s_hit >= Pk(sc.near_)) & (s_hit <= Pk(sc.far_)), s_hit, inf);
      X.s_n[S] = sn;
      X.dist[S] = dist;
      for (int k = 0; k < 4; ++k) X.alb[4 * S + k] = X.param(geo, S, 15 + k);
      ++S;
    }
  }
  // first hit: segmentation, body, hard depth
  Pk first = 0, best = S ? X.s_hit[0] : inf;
  Mk any_hit = S ? Finite(X.s_hit[0]) : Mk(false);
  for (int k = 1; k < S; ++k) {
    Mk up = X.s_hit[k] < best;
    best = sel(up, X.s_hit[k], best), first = sel(up, Pk(double(k)), first);
    any_hit |= Finite(X.s_hit[k]);
  }
  for (int k = 0; k < S; ++k) {
    Pk zk;
    if (!soft) {
      Mk h = Finite(X.s_hit[k]);
      zk = sel(h, X.s_hit[k], Pk(sc.far_));
      X.cover[k] = sel(h, Pk(1), Pk(0));
    } else {
      zk = X.s_n[k];
      Pk d_px = X.dist[k] / (Max(zk, Pk(sc.near_)) * Pk(px));
      X.cover[k] = sigmoid(-d_px / Pk(sc.tau)) *
                   sel((zk >= Pk(sc.near_)) & (zk <= Pk(sc.far_)), Pk(1), Pk(0));
    }
    X.z[k] = zk;
    for (int q = 0; q < 3; ++q) X.p[3 * k + q] = O[q] + zk * r[q];
  }
  // The `layers` most covering surfaces not hidden behind a solid one (render_jax's
  // top_k over all its slots, ties to the lower one; a surface of negligible coverage ranks
  // below every other), taken as every slot here in order with its coverage set to 0 in the
  // lanes whose choice leaves it out: a slot left out above, or a layer of coverage 0, adds
  // exactly nothing to the composite or its gradient; of negligible coverage, nothing that
  // shows (renderer.negligible_coverage).
  R.any_dropped = false;
  if (sc.slots > sc.layers) {
    Pk solid = inf;
    for (int k = 0; k < S; ++k) solid = sel(X.cover[k] > Pk(0.999), Min(solid, X.z[k]), solid);
    Mk ranked[64];
    for (int k = 0; k < S; ++k) {
      Mk shown = X.z[k] <= solid + Pk(soft ? T(10) * sc.gamma : T(0));
      X.key[k] = sel(shown, X.cover[k] - Pk(1e-6) * X.z[k] / Pk(sc.far_),
                     Pk(-1) - X.z[k] / Pk(sc.far_));
      ranked[k] = X.cover[k] >= Pk(sc.negligible);
    }
    for (int s = 0; s < S; ++s) {
      // how many slots top_k takes before s (a larger key, or an equal one at a lower index)
      Pk before = 0;
      for (int k = 0; k < S; ++k)
        if (k != s)
          before += sel(ranked[k] & ((X.key[k] > X.key[s]) | ((X.key[k] == X.key[s]) & Mk(k < s))),
                        Pk(1), Pk(0));
      X.kept[s] = ranked[s] & (before < Pk(double(sc.layers)));
      R.any_dropped = R.any_dropped || !all(X.kept[s]);
    }
  }
  R.S = S, R.first = first, R.first_hit = best, R.any_hit = any_hit;
}

// A packet's composite over its `layers` surfaces: coverage, depth, weights of the depth image
// (w, bg) and of the colour (wrgb: coverage times alpha), and the shadow factors.
template <typename T>
void mix(const Scene<T>& sc, const T* geo, Scratch<T>& X, const Ray<T>& R) {
  using Pk = P<T>;
  const bool soft = sc.tau != 0;
  const int L = R.S;
  for (int k = 0; k < L; ++k) {
    X.a[k] = R.any_dropped ? sel(X.kept[k], X.cover[k], Pk(0)) : X.cover[k];
    X.zz[k] = X.z[k];
    X.alpha[k] = X.alb[4 * k + 3];
  }
  depth_order(L, X.a.data(), X.zz.data(), soft, sc.gamma, X.ahead.data());
  composite(L, X.a.data(), X.ahead.data(), X.w.data(), X.bg);
  if (sc.shadows && sc.any_shadow && L > 0) {
    // one shadow ray a pixel, from the surface that shows most there
    Pk win = 0, wb = X.w[0];
    for (int k = 1; k < L; ++k) {
      auto up = X.w[k] > wb;
      wb = sel(up, X.w[k], wb), win = sel(up, Pk(double(k)), win);
    }
    Pk pw[3], gw;
    for (int q = 0; q < 3; ++q) pw[q] = pick_lanes(X.p.data(), 3, win, q);
    for (int l = 0; l < Pk::N; ++l) gw.v[l] = T(X.gid[int(win[l])]);
    for (int li = 0; li < sc.NL; ++li) {
      if (sc.light[li * kLightStride + 21] == 0) continue;
      Pk l[3], dist;
      sc.light_dir(li, pw, l, dist, nullptr);
      X.lit[li] = sc.unoccluded(geo, X.frb.data(), pw, l, dist, gw, li);
    }
  }
  for (int k = 0; k < L; ++k) X.wa[k] = X.a[k] * X.alpha[k];
  composite(L, X.wa.data(), X.ahead.data(), X.wrgb.data(), X.bg_rgb);
}

// slot s's unit world normal n (and the local one, nl, and world nw it is made from)
template <typename T>
void surface_normal(const Scene<T>& sc, const T* geo, const Scratch<T>& X, const Ray<T>& R,
                    int s, P<T>* nl, P<T>* nw, P<T>* n, P<T>& nn, P<T>* xm) {
  using Pk = P<T>;
  Pk sz[3];
  for (int k = 0; k < 3; ++k) sz[k] = X.param(geo, s, 12 + k);
  for (int k = 0; k < 9; ++k) xm[k] = X.param(geo, s, 3 + k);
  normal(X.type[s], &X.pl[3 * s], sz, sc.tau != 0, Pk(sc.tau * R.px) * X.s_n[s], nl);
  to_world(nl, xm, nw);
  nn = Sqrt(dot3(nw, nw) + Pk(1e-20));
  for (int q = 0; q < 3; ++q) n[q] = nw[q] / nn;
}

// where a packet's lanes write: the pixel index of each lane inside the image, -1 outside
template <typename T>
inline void lane_pixels(int64_t b, int i0, int j0, int64_t H, int64_t W, int64_t* px) {
  for (int l = 0; l < P<T>::N; ++l) {
    int64_t i = i0 + l / tile_w<T>(), j = j0 + l % tile_w<T>();
    px[l] = (i < H && j < W) ? (b * H + i) * W + j : -1;
  }
}

template <typename T>
void draw_packet(const Scene<T>& sc, const T* cam, const T* geo, int i0, int j0, int64_t H,
                 int64_t W, int64_t b, Scratch<T>& X, const int64_t* pix, T* rgb, T* depth,
                 int32_t* seg, int32_t* body, T* weights, T* background) {
  using Pk = P<T>;
  Ray<T> R;
  gather(sc, cam, geo, i0, j0, H, W, b, X, R);
  mix(sc, geo, X, R);
  const int L = R.S;
  Pk out[3] = {0, 0, 0};
  for (int s = 0; s < R.S; ++s) {
    // a surface that adds nothing here is not shaded: the hard image's hidden ones (weight
    // exactly 0), the soft one's far from their silhouette (coverage under 1e-12)
    const Pk& wr = X.wrgb[s];
    auto shown = wr > Pk(1e-12);
    if (none(shown)) continue;
    Pk nl[3], nw[3], n[3], nn, xm[9], col[3], mat[3];
    surface_normal(sc, geo, X, R, s, nl, nw, n, nn, xm);
    X.material(sc, s, mat);
    sc.shade(&X.p[3 * s], n, cam, R.fwd, &X.alb[4 * s], mat, X.lit.data(), col);
    for (int q = 0; q < 3; ++q) out[q] = out[q] + sel(shown, wr * col[q], Pk(0));
  }
  Pk dep;
  if (sc.tau != 0) {
    Pk dsum = 0;
    for (int k = 0; k < L; ++k) dsum = k == 0 ? X.w[0] * X.zz[0] : dsum + X.w[k] * X.zz[k];
    dep = dsum + X.bg * Pk(sc.far_depth);
  } else {
    dep = sel(R.any_hit, R.first_hit, Pk(sc.far_depth));
  }
  const int G = sc.G;
  // every geom a slot: every weight is written once, none need zeroing
  const bool every = R.S == G;
  for (int l = 0; l < Pk::N; ++l) {
    int64_t p = pix[l];
    if (p < 0) continue;
    int g = X.gid[int(R.first[l])];
    seg[p] = R.any_hit[l] ? sc.gids[g] : -1;
    body[p] = R.any_hit[l] ? sc.bodies[g] : -1;
    for (int q = 0; q < 3; ++q) rgb[3 * p + q] = out[q][l];
    depth[p] = dep[l];
    background[p] = X.bg[l];
    if (!every) std::fill(weights + int64_t(G) * p, weights + int64_t(G) * (p + 1), T(0));
  }
  // each slot a geom of its own
  for (int s = 0; s < R.S; ++s) {
    const Pk& ws = X.w[s];
    for (int l = 0; l < Pk::N; ++l)
      if (pix[l] >= 0) weights[int64_t(G) * pix[l] + X.gid[s]] = ws[l];
  }
}

// ------------------------------------------------------------------ the reverse pass
// The gradient of <cotangent, image> with respect to the camera and the geoms, packet by packet:
// the packet is drawn again (gather, mix), then differentiated backwards by hand through the
// composite and the shading down to each surface's depth, distance and normal, and from those
// to the surface's inputs (the ray and camera in the geom's frame, its size, the pixel size)
// through that surface's Jacobian, found on Dual numbers by the same templates that drew it.

// the composite's reverse (every pair, as JAX takes them: a pair with a zero coverage has
// occlusion exactly 1 either way, but its derivative need not be 0); occl: L * L scratch
template <typename T>
void composite_vjp(int L, const P<T>* a, const P<T>* ahead, const P<T>* dw, const P<T>& dbg,
                   P<T>* da, P<T>* dahead, P<T>* occl) {
  using Pk = P<T>;
  Pk Pg[64], u[64];
  Pk B = 1, tot = 0;
  for (int g = 0; g < L; ++g) {
    Pk prod = 1;
    for (int k = 0; k < L; ++k) {
      Pk o = k == g ? Pk(1) : Pk(1) - a[k] * ahead[g * L + k];
      occl[g * L + k] = o;
      prod = k == 0 ? o : prod * o;
    }
    Pg[g] = prod;
    u[g] = a[g] * prod;
    tot = g == 0 ? u[0] : tot + u[g];
    B = g == 0 ? Pk(1) - a[0] : B * (Pk(1) - a[g]);
  }
  tot = tot + B;
  auto pos = tot > Pk(0);
  Pk t = sel(pos, tot, Pk(1));
  Pk dtot = 0;
  for (int g = 0; g < L; ++g) dtot -= dw[g] * u[g];
  dtot = sel(pos, (dtot - dbg * B) / (t * t), Pk(0));
  Pk dB = dbg / t + dtot;
  Pk pre[65], suf[65];
  for (int g = 0; g < L; ++g) {
    Pk du = dw[g] / t + dtot;
    da[g] += du * Pg[g];
    Pk coef = du * a[g];
    if (all(coef == Pk(0))) continue;
    const Pk* og = &occl[g * L];
    pre[0] = 1;
    for (int k = 0; k < L; ++k) pre[k + 1] = pre[k] * og[k];
    suf[L] = 1;
    for (int k = L - 1; k >= 0; --k) suf[k] = suf[k + 1] * og[k];
    for (int k = 0; k < L; ++k) {
      if (k == g) continue;
      Pk d_o = coef * pre[k] * suf[k + 1];
      da[k] -= d_o * ahead[g * L + k];
      dahead[g * L + k] -= d_o * a[k];
    }
  }
  if (any(dB != Pk(0))) {
    pre[0] = 1;
    for (int k = 0; k < L; ++k) pre[k + 1] = pre[k] * (Pk(1) - a[k]);
    suf[L] = 1;
    for (int k = L - 1; k >= 0; --k) suf[k] = suf[k + 1] * (Pk(1) - a[k]);
    for (int k = 0; k < L; ++k) da[k] -= dB * pre[k] * suf[k + 1];
  }
}

// d clip(x, 0, 1) / dx as JAX's (ties half)
template <typename T>
inline P<T> clip_slope(const P<T>& x) {
  using Pk = P<T>;
  Pk lo = sel(x > Pk(0), Pk(1), sel(x == Pk(0), Pk(0.5), Pk(0)));
  Pk hi = sel(x < Pk(1), Pk(1), sel(x == Pk(1), Pk(0.5), Pk(0)));
  return lo * hi;
}
template <typename T>
inline P<T> relu_slope(const P<T>& x) {
  return sel(x > P<T>(0), P<T>(1), sel(x == P<T>(0), P<T>(0.5), P<T>(0)));
}

// the reverse of x / sqrt(x.x + 1e-20) (y, its value; nn, the root): dx from dy
template <typename T>
inline void unit_vjp(const T* y, const T& nn, const T* dy, T* dx) {
  T yd = dot3(y, dy);
  for (int k = 0; k < 3; ++k) dx[k] += (dy[k] - y[k] * yd) / nn;
}

// Scene::shade's reverse: dcol (the clamped colour's cotangent) to p, n, the camera position o,
// the view direction fwd and the albedo's rgb (all added to); out: the colour Scene::shade gives;
// E: scratch for the lights' terms (NL + 1)
template <typename T>
void shade_vjp(const Scene<T>& sc, const P<T>* p, const P<T>* n, const T* o, const T* fwd,
               const P<T>* alb, const P<T>* mat, const P<T>* lit, const P<T>* dcol_clamped,
               P<T>* dp, P<T>* dn, P<T>* d_o, P<T>* dfwd, P<T>* dalb, P<T>* out,
               LightTerms<T>* E) {
  using Pk = P<T>;
  using Mk = Mask<T>;
  Pk col[3];
  Pk v0[3];
  for (int k = 0; k < 3; ++k) v0[k] = Pk(o[k]) - p[k];
  Pk vn = Sqrt(dot3(v0, v0) + Pk(1e-20));
  Pk v[3] = {v0[0] / vn, v0[1] / vn, v0[2] / vn};
  Pk spec_m = mat[0], sh = Pk(128) * mat[1], emis = mat[2];
  // the unclamped colour (to know where the clamp passes the gradient)
  for (int k = 0; k < 3; ++k) col[k] = emis * alb[k];
  // light q (the headlight first where it is on)
  const int ne = sc.NL + (sc.head_on ? 1 : 0);
  for (int q = 0; q < ne; ++q) {
    LightTerms<T>& e = E[q];
    if (sc.head_on && q == 0) {
      for (int k = 0; k < 3; ++k) e.l[k] = Pk(-fwd[k]);
      e.amb = sc.head, e.dif = sc.head + 3, e.spe = sc.head + 6;
      e.factor = 1, e.kind = 0, e.index = -1;
    } else {
      int i = q - (sc.head_on ? 1 : 0);
      const T* L = &sc.light[i * kLightStride];
      sc.light_dir(i, p, e.l, e.dist, &e.factor, &e.f0, &e.spot);
      if (sc.shadows && L[21] != 0) e.factor = e.factor * lit[i];
      e.amb = L + 7, e.dif = L + 10, e.spe = L + 13;
      e.kind = int(L[0]) == 1 ? 1 : 2;
      e.index = i;
    }
    e.ndl = dot3(n, e.l);
    Pk h0[3];
    for (int k = 0; k < 3; ++k) h0[k] = e.l[k] + v[k];
    e.hn = Sqrt(dot3(h0, h0) + Pk(1e-20));
    for (int k = 0; k < 3; ++k) e.h[k] = h0[k] / e.hn;
    e.nh = dot3(n, e.h);
    e.ndh = Max(e.nh, Pk(0));
    Mk lit_side = e.ndl > Pk(0);
    e.sp = any(lit_side) ? sel(lit_side, Exp(sh * Log(e.ndh + Pk(1e-30))), Pk(0)) : Pk(0);
    e.nd = Max(e.ndl, Pk(0));
    for (int k = 0; k < 3; ++k)
      col[k] = col[k] + Pk(e.amb[k]) * alb[k] +
               e.factor * (Pk(e.dif[k]) * e.nd * alb[k] + Pk(e.spe[k]) * spec_m * e.sp);
  }
  Pk dcol[3];
  for (int k = 0; k < 3; ++k) {
    dcol[k] = dcol_clamped[k] * clip_slope(col[k]);
    out[k] = Min(Max(col[k], Pk(0)), Pk(1));
  }
  if (all((dcol[0] == Pk(0)) & (dcol[1] == Pk(0)) & (dcol[2] == Pk(0)))) return;
  Pk dv[3] = {0, 0, 0};
  for (int k = 0; k < 3; ++k) dalb[k] += dcol[k] * emis;
  for (int q = 0; q < ne; ++q) {
    const LightTerms<T>& e = E[q];
    Pk dfactor = 0, dnd = 0, dsp = 0;
    for (int k = 0; k < 3; ++k) {
      dalb[k] += dcol[k] * (Pk(e.amb[k]) + e.factor * Pk(e.dif[k]) * e.nd);
      dfactor += dcol[k] * (Pk(e.dif[k]) * e.nd * alb[k] + Pk(e.spe[k]) * spec_m * e.sp);
      dnd += dcol[k] * Pk(e.dif[k]) * alb[k];
      dsp += dcol[k] * Pk(e.spe[k]);
    }
    dnd *= e.factor;
    dsp *= e.factor * spec_m;
    Pk dndl = dnd * relu_slope(e.ndl);
    Pk dndh = sel(e.ndl > Pk(0), dsp * e.sp * sh / (e.ndh + Pk(1e-30)), Pk(0));
    Pk dnh = dndh * relu_slope(e.nh);
    Pk dl[3], dh0[3] = {0, 0, 0};
    Pk dh[3];
    for (int k = 0; k < 3; ++k) {
      dn[k] += dnh * e.h[k] + dndl * e.l[k];
      dh[k] = dnh * n[k];
      dl[k] = dndl * n[k];
    }
    unit_vjp(e.h, e.hn, dh, dh0);
    for (int k = 0; k < 3; ++k) dl[k] += dh0[k], dv[k] += dh0[k];
    if (e.kind == 0) {
      for (int k = 0; k < 3; ++k) dfwd[k] -= dl[k];
    } else if (e.kind == 2) {
      // l = (pos - p) / dist, factor = lit / (a0 + a1 dist + a2 dist^2) [x spot(cos)]
      const T* L = &sc.light[e.index * kLightStride];
      Pk dlv[3];
      for (int k = 0; k < 3; ++k) dlv[k] = Pk(L[1 + k]) - p[k];
      const Pk& dist = e.dist;
      const Pk& f0 = e.f0;
      Pk shadow = (sc.shadows && L[21] != 0) ? lit[e.index] : Pk(1);
      Pk spot = 1;
      if (int(L[0]) == 0) {
        Pk cosang = -dot3m(e.l, L + 4);
        Mk inside = cosang >= Pk(sc.cutoff_cos[e.index]);
        spot = e.spot;
        Pk dspot = dfactor * f0 * shadow;
        Pk dcos = sel(inside & (cosang > Pk(1e-30)), dspot * spot * Pk(L[17]) / cosang, Pk(0));
        for (int k = 0; k < 3; ++k) dl[k] -= dcos * Pk(L[4 + k]);
      }
      Pk df0 = dfactor * spot * shadow;
      Pk ddist = -df0 * f0 * f0 * (Pk(L[19]) + Pk(2) * Pk(L[20]) * dist);
      Pk ldl = dot3(dl, dlv);
      Pk ddlv[3];
      for (int k = 0; k < 3; ++k) ddlv[k] = dl[k] / dist;
      ddist -= ldl / (dist * dist);
      for (int k = 0; k < 3; ++k) dp[k] -= ddlv[k] + ddist * dlv[k] / dist;
    }
  }
  Pk dv0[3] = {0, 0, 0};
  unit_vjp(v, vn, dv, dv0);
  for (int k = 0; k < 3; ++k) d_o[k] += dv0[k], dp[k] -= dv0[k];
}

constexpr int kIn = 10;  // a surface's inputs: the camera (3) and ray (3) in the geom's frame,
                         // the geom's size (3), the pixel size

// Slot s's Jacobian applied to the cotangents of its first hit, placed depth, signed distance
// and local normal: the cotangents of its kIn inputs (g_in, overwritten), lane by lane
template <typename T>
void surface_vjp(const Scene<T>& sc, const T* geo, const Scratch<T>& X, T px, int s,
                 const P<T>& d_hit, const P<T>& d_sn, const P<T>& d_dist, const P<T>* d_nl,
                 Mask<T> normal_needed, P<T>* g_in) {
  using Pk = P<T>;
  using D = Dual<Pk, kIn>;
  const bool soft = sc.tau != 0;
  const int t = X.type[s];
  const Pk* ol = &X.ol[3 * s];
  const Pk* rlv = &X.rl[3 * s];
  D o[3], r[3], sz[3];
  for (int k = 0; k < 3; ++k) {
    o[k] = D::seed(ol[k], k);
    r[k] = D::seed(rlv[k], 3 + k);
    sz[k] = D::seed(X.param(geo, s, 12 + k), 6 + k);
  }
  D Pd = D::seed(Pk(px), 9);
  const D inf = K<D>::inf();
  const auto miss = X.miss[s];
  D s_hit = all(miss) ? inf : sel(miss, inf, hit(t, o, r, sz));
  D sn, dist(0.0);
  if (!soft) {
    sn = s_hit;
  } else if (none(!((d_dist == Pk(0)) & Finite(s_hit)))) {
    sn = s_hit;  // the closest approach would only give the distance, which nothing needs
  } else {
    D s_c;
    closest(t, o, r, sz, sc.iters, s_c, dist);
    sn = sel(Finite(s_hit), s_hit, s_c);
    sn = sel(Finite(sn), sn, D(sc.far_));
  }
  for (int k = 0; k < kIn; ++k) g_in[k] = 0;
  auto add = [&](const D& x, const Pk& c) {
    auto on = c != Pk(0);
    if (none(on)) return;
    for (int k = 0; k < kIn; ++k) g_in[k] += sel(on, c * x.d[k], Pk(0));
  };
  add(s_hit, d_hit);
  add(sn, d_sn);
  add(dist, d_dist);
  if (any(normal_needed)) {
    D sp = soft ? sn : sel(Finite(s_hit), s_hit, D(sc.far_));
    D pl[3], nl[3];
    for (int k = 0; k < 3; ++k) pl[k] = o[k] + sp * r[k];
    D tn = D(sc.tau) * Pd * sn;
    normal(t, pl, sz, soft, tn, nl);
    for (int k = 0; k < 3; ++k) add(nl[k], sel(normal_needed, d_nl[k], Pk(0)));
  }
}

// The packet's contribution to the gradients (X.gcam, X.ggeo: this frame's, lane by lane), from
// the cotangents of its pixels' colour (c_rgb), depth, per-geom weights (cw: the batch's array,
// read at each lane's pixel `pix`, 0 outside the image; null where 0 over the packet) and
// background
template <typename T>
void draw_packet_vjp(const Scene<T>& sc, const T* cam, const T* geo, int i0, int j0,
                     int64_t H, int64_t W, int64_t b, Scratch<T>& X, const int64_t* pix,
                     const P<T>* c_rgb, const P<T>& c_depth, const T* cw, const P<T>& c_bg) {
  using Pk = P<T>;
  using Mk = Mask<T>;
  const bool soft = sc.tau != 0;
  const int G = sc.G;
  Ray<T> R;
  gather(sc, cam, geo, i0, j0, H, W, b, X, R);
  mix(sc, geo, X, R);
  const int L = R.S, S = R.S;
  const Pk* r = R.r;
  // cotangents per layer and per slot
  for (int k = 0; k < S; ++k) {
    X.d_hit[k] = X.d_sn[k] = X.d_dist[k] = X.d_z[k] = 0;
    X.d_nl[3 * k] = X.d_nl[3 * k + 1] = X.d_nl[3 * k + 2] = 0;
    X.shaded[k] = false;
  }
  Pk d_bg = c_bg;
  for (int k = 0; k < L; ++k) {  // the weights' cotangent at each lane's pixel
    Pk dw = 0;
    if (cw)
      for (int l = 0; l < Pk::N; ++l)
        if (pix[l] >= 0) dw.v[l] = cw[int64_t(G) * pix[l] + X.gid[k]];
    X.d_w[k] = dw;
    X.d_zz[k] = X.d_a[k] = X.d_wa[k] = X.d_wrgb[k] = 0;
  }
  if (soft) {
    for (int k = 0; k < L; ++k) X.d_w[k] += c_depth * X.zz[k], X.d_zz[k] += c_depth * X.w[k];
    d_bg += c_depth * Pk(sc.far_depth);
  } else {
    for (int s = 0; s < S; ++s)
      X.d_hit[s] += sel(R.any_hit & (R.first == Pk(double(s))), c_depth, Pk(0));
  }
  Pk d_o[3] = {0, 0, 0}, d_r[3] = {0, 0, 0}, d_fwd[3] = {0, 0, 0}, d_px = 0;
  for (int s = 0; s < S; ++s) {
    // A surface's colour matters where it is drawn (wrgb) and, through the derivative of its
    // weight, wherever it covers the pixel (wa): hidden behind an opaque one, its colour is
    // what that one's alpha lets through. (Under 1e-12 either way, nothing is lost.)
    const Pk& wa = X.wa[s];
    Mk covers = wa > Pk(1e-12);
    if (none(covers)) continue;
    const Pk& wr = X.wrgb[s];
    Mk drawn = covers & (wr > Pk(1e-12));
    Pk nl[3], nw[3], n[3], nn, xm[9], col[3], mat[3];
    surface_normal(sc, geo, X, R, s, nl, nw, n, nn, xm);
    X.material(sc, s, mat);
    Pk w_on = sel(drawn, wr, Pk(0));
    Pk dcol[3] = {w_on * c_rgb[0], w_on * c_rgb[1], w_on * c_rgb[2]};
    Pk dp[3] = {0, 0, 0}, dn[3] = {0, 0, 0}, dalb[3] = {0, 0, 0}, dos[3] = {0, 0, 0};
    Pk dfw[3] = {0, 0, 0};
    shade_vjp(sc, &X.p[3 * s], n, cam, R.fwd, &X.alb[4 * s], mat, X.lit.data(), dcol, dp, dn,
              dos, dfw, dalb, col, X.lights.data());
    X.d_wrgb[s] = sel(covers, dot3(c_rgb, col), Pk(0));
    if (none(drawn)) continue;
    for (int q = 0; q < 3; ++q) X.add_geom(s, 15 + q, sel(drawn, dalb[q], Pk(0)));
    for (int q = 0; q < 3; ++q) dn[q] = sel(drawn, dn[q], Pk(0));
    Pk dnw[3] = {0, 0, 0};
    unit_vjp(n, nn, dn, dnw);
    for (int a = 0; a < 3; ++a)
      for (int b = 0; b < 3; ++b) {
        X.d_nl[3 * s + b] += dnw[a] * xm[3 * a + b];
        X.add_geom(s, 3 + 3 * a + b, dnw[a] * nl[b]);
      }
    X.shaded[s] = drawn;
    // p = o + z r
    for (int q = 0; q < 3; ++q) {
      dp[q] = sel(drawn, dp[q], Pk(0));
      d_o[q] += sel(drawn, dos[q], Pk(0)) + dp[q];
      d_fwd[q] += sel(drawn, dfw[q], Pk(0));
      d_r[q] += X.z[s] * dp[q];
    }
    X.d_z[s] += dot3(dp, r);
  }
  // the composites (the depth image's only where soft: the hard one's weights are constants)
  Pk* ahead = X.ahead.data();
  depth_order(L, X.a.data(), X.zz.data(), soft, sc.gamma, ahead, true);
  Pk* dahead = X.dahead.data();
  for (int q = 0; q < L * L; ++q) dahead[q] = 0;
  composite_vjp(L, X.wa.data(), ahead, X.d_wrgb.data(), Pk(0), X.d_wa.data(), dahead,
                X.occl.data());
  for (int k = 0; k < L; ++k) {
    X.add_geom(k, 18, X.d_wa[k] * X.a[k]);
    X.d_a[k] += X.d_wa[k] * X.alpha[k];
  }
  if (soft) {
    composite_vjp(L, X.a.data(), ahead, X.d_w.data(), d_bg, X.d_a.data(), dahead, X.occl.data());
    for (int g = 0; g < L; ++g)
      for (int k = g + 1; k < L; ++k) {
        Pk h = ahead[g * L + k];
        Pk dz = (dahead[g * L + k] - dahead[k * L + g]) * h * (Pk(1) - h) / Pk(sc.gamma);
        X.d_zz[g] += dz, X.d_zz[k] -= dz;
      }
    for (int k = 0; k < L; ++k) {
      const int s = k;
      X.d_z[s] += X.d_zz[k];
      Pk c = X.a[k];
      // masked (outside near..far), or so far in or out that the sigmoid is flat: a derivative
      // under 1e-10 of the others (and the distance need not be differentiated at all)
      Mk steep = c * (Pk(1) - c) > Pk(1e-10);
      if (none(steep)) continue;
      Pk sn = X.s_n[s], dist = X.dist[s];
      Pk M_ = Max(sn, Pk(sc.near_));
      Pk den = M_ * Pk(R.px) * Pk(sc.tau);
      Pk dx = X.d_a[k] * c * (Pk(1) - c);
      X.d_dist[s] += sel(steep, -dx / den, Pk(0));
      Pk dM = dx * dist / (den * M_);
      X.d_sn[s] += sel(steep, dM * relu_slope(sn - Pk(sc.near_)), Pk(0));
      d_px += sel(steep, dx * dist / (den * Pk(R.px)), Pk(0));
    }
    for (int s = 0; s < S; ++s) {
      X.d_sn[s] += X.d_z[s];
      // adds nothing to the pixel
      X.d_sn[s] = sel(!(X.cover[s] > Pk(1e-10)) & !X.shaded[s], Pk(0), X.d_sn[s]);
    }
  } else {
    for (int s = 0; s < S; ++s) X.d_hit[s] += sel(Finite(X.s_hit[s]), X.d_z[s], Pk(0));
  }
  // each surface's inputs
  for (int s = 0; s < S; ++s) {
    Mk on = ((X.d_hit[s] != Pk(0)) | (X.d_sn[s] != Pk(0)) | (X.d_dist[s] != Pk(0)) |
             X.shaded[s]) & !X.far[s];
    if (none(on)) continue;
    Pk g_in[kIn], dnl[3];
    for (int q = 0; q < 3; ++q) dnl[q] = sel(on, X.d_nl[3 * s + q], Pk(0));
    surface_vjp(sc, geo, X, R.px, s, sel(on, X.d_hit[s], Pk(0)), sel(on, X.d_sn[s], Pk(0)),
                sel(on, X.d_dist[s], Pk(0)), dnl, X.shaded[s] & on, g_in);
    Pk m[9], xp[3];
    for (int k = 0; k < 9; ++k) m[k] = X.param(geo, s, 3 + k);
    for (int k = 0; k < 3; ++k) xp[k] = X.param(geo, s, k);
    for (int a = 0; a < 3; ++a) {
      Pk t_o = 0, t_r = 0;
      for (int b = 0; b < 3; ++b) {
        t_o += g_in[b] * m[3 * a + b];
        t_r += g_in[3 + b] * m[3 * a + b];
        X.add_geom(s, 3 + 3 * a + b, (Pk(cam[a]) - xp[a]) * g_in[b] + r[a] * g_in[3 + b]);
      }
      d_o[a] += t_o;
      X.add_geom(s, a, -t_o);
      d_r[a] += t_r;
      X.add_geom(s, 12 + a, g_in[6 + a]);
    }
    d_px += g_in[9];
  }
  // the ray r = cm loc, loc = ((j + 0.5 - cx) px, (cy - i - 0.5) px, -1); fwd = -cm[:, 2]
  const T* cm = cam + 3;
  T px = cam[12], cx = cam[13], cy = cam[14];
  Pk lx = R.jj + Pk(0.5) - Pk(cx), ly = Pk(cy) - R.ii - Pk(0.5);
  Pk loc[3] = {lx * Pk(px), ly * Pk(px), Pk(-1)};
  Pk dloc[3] = {0, 0, 0};
  Pk* gcam = X.gcam.data();
  for (int a = 0; a < 3; ++a)
    for (int c = 0; c < 3; ++c) {
      gcam[3 + 3 * a + c] += d_r[a] * loc[c];
      dloc[c] += d_r[a] * Pk(cm[3 * a + c]);
    }
  for (int a = 0; a < 3; ++a) gcam[3 + 3 * a + 2] -= d_fwd[a], gcam[a] += d_o[a];
  d_px += dloc[0] * lx + dloc[1] * ly;
  gcam[12] += d_px;
  gcam[13] -= dloc[0] * Pk(px);
  gcam[14] += dloc[1] * Pk(px);
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
    T* ol = &X.fol[3 * k];
    for (int j = 0; j < 3; ++j) ol[j] = (d[0] * gp[3 + j] + d[1] * gp[6 + j]) + d[2] * gp[9 + j];
    X.foo[k] = (ol[0] * ol[0] + ol[1] * ol[1]) + ol[2] * ol[2];
    X.frb[k] = bound_radius(sc.types[k], gp + 12);
  }
  X.frame = b;
}

// packet(worker, scene, scratch, cam, geo, frame, row, column) for every packet of the batch
// (the top-left pixel's row and column), the rows of packets split over nw workers, each with
// its own copy of the scene (its frames' temperatures) and its own scratch; finish(worker,
// scratch) when a worker is done
template <typename T, typename F, typename E>
void for_packets(const Scene<T>& sc, const T* camp, const T* geop, const T* tgp, int64_t N,
                 int64_t H, int64_t W, const F& packet, const E& finish) {
  const int TH = tile_h<T>(), TW = tile_w<T>();
  const int64_t rows = (H + TH - 1) / TH, cols = (W + TW - 1) / TW;
  parallel_rows(worker_count(N * rows), N * rows, [&](int worker, int64_t r0, int64_t r1) {
    Scene<T> S = sc;
    Scratch<T> X(sc.slots, sc.G, sc.NL);
    for (int64_t row = r0; row < r1; ++row) {
      int64_t b = row / rows;
      int i0 = int(row % rows) * TH;
      const T* c = camp + 15 * b;
      const T* g = geop + int64_t(19) * sc.G * b;
      begin_frame(S, X, c, g, tgp, b);
      for (int64_t tj = 0; tj < cols; ++tj) packet(worker, S, X, c, g, b, i0, int(tj) * TW);
    }
    finish(worker, X);
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
  for_packets(
      sc, camp, geop, tgp, N, H, W,
      [&](int, const Scene<T>& S, Scratch<T>& X, const T* c, const T* g, int64_t b, int i0,
          int j0) {
        int64_t pix[P<T>::N];
        lane_pixels<T>(b, i0, j0, H, W, pix);
        draw_packet(S, c, g, i0, j0, H, W, b, X, pix, rgbp, depp, segp, bodp, wp, bgp);
      },
      [](int, Scratch<T>&) {});
  return ffi::Error::Success();
}


// The reverse kernel: cotangents of rgb (..., H, W, 3), depth, weights (..., H, W, G) and
// background to those of cam (..., 15) and geo (..., G, 19). Each worker adds its frames'
// packets into its own copy of the gradients (lane by lane within a frame); the copies are
// summed at the end.
template <typename T, ffi::DataType DT>
ffi::Error RenderVjp(ffi::Buffer<DT> cam, ffi::Buffer<DT> geo, ffi::Buffer<DT> tg,
                     ffi::Buffer<DT> c_rgb,
                     ffi::Buffer<DT> c_depth, ffi::Buffer<DT> c_w, ffi::Buffer<DT> c_bg,
                     ffi::ResultBuffer<DT> gcam, ffi::ResultBuffer<DT> ggeo, Config cfg) {
  using Pk = P<T>;
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
  const int64_t ncam = N * 15, ngeo = N * G * 19;
  const int TH = tile_h<T>();
  int nw = worker_count(N * ((H + TH - 1) / TH));
  std::vector<std::vector<T>> acc(nw, std::vector<T>(ncam + ngeo, T(0)));
  // a worker's lane-by-lane sums of its frame (X.acc_frame) into its copy of the gradients
  auto flush = [&](int worker, Scratch<T>& X) {
    if (X.acc_frame < 0) return;
    T* a = acc[worker].data();
    int64_t b = X.acc_frame;
    for (int q = 0; q < 15; ++q) a[15 * b + q] += hsum(X.gcam[q]), X.gcam[q] = Pk(0);
    for (int q = 0; q < 19 * G; ++q)
      a[ncam + int64_t(19) * G * b + q] += hsum(X.ggeo[q]), X.ggeo[q] = Pk(0);
    X.acc_frame = -1;
  };
  for_packets(
      sc, camp, geop, tgp, N, H, W,
      [&](int worker, const Scene<T>& S, Scratch<T>& X, const T* c, const T* g, int64_t b,
          int i0, int j0) {
        int64_t pix[Pk::N];
        lane_pixels<T>(b, i0, j0, H, W, pix);
        Pk cr[3] = {0, 0, 0}, cd = 0, cb = 0;
        bool zero = true, w_zero = true;
        for (int l = 0; l < Pk::N; ++l) {
          int64_t p = pix[l];
          if (p < 0) continue;
          for (int q = 0; q < 3; ++q) cr[q].v[l] = crgb[3 * p + q];
          cd.v[l] = cdep[p], cb.v[l] = cbg[p];
          zero = zero && cr[0][l] == 0 && cr[1][l] == 0 && cr[2][l] == 0 && cd[l] == 0 &&
                 cb[l] == 0;
          const T* cwp = cw + int64_t(G) * p;
          for (int k = 0; w_zero && k < G; ++k) w_zero = cwp[k] == 0;
        }
        if (zero && w_zero) return;  // (a crop's loss, a masked pixel)
        if (X.acc_frame != b) flush(worker, X), X.acc_frame = b;
        draw_packet_vjp(S, c, g, i0, j0, H, W, b, X, pix, cr, cd, w_zero ? nullptr : cw, cb);
      },
      flush);
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
