// Forward and backward compositing of the CPU rasterizer, 16 pixels of a tile row at a time.
//
// The same rules and array layouts as the Numba kernels of _cpu_kernels.py (see there): per
// pixel, the depth-sorted entries of its tile front to back, alpha = min(0.999, opacity *
// exp(-sigma)), sigma < 0 or alpha < 1/255 skipped, a pixel stops before the entry that would
// bring its transmittance to <= 1e-4. Arithmetic is float32 in vectors of 16 lanes (one AVX-512
// register, two AVX2 ones); exp is a polynomial with the exponent put in by integer arithmetic.
//
// Each tile is the work of one thread, in a fixed order inside it, and the lanes of a
// per-entry gradient are summed in a fixed order, so the bytes do not depend on the number of
// threads. Threads take tiles from a shared counter.
//
// Built by _native.py with the machine's C++ compiler and loaded through ctypes.

#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <thread>
#include <vector>

#if defined(__AVX512F__) || defined(__AVX2__)
#include <immintrin.h>
#endif

namespace {

constexpr int L = 16;
typedef float vf __attribute__((vector_size(4 * L)));
typedef int32_t vi __attribute__((vector_size(4 * L)));

constexpr float ALPHA_MIN = 1.0f / 255.0f;
constexpr float ALPHA_MAX = 0.999f;
constexpr float T_MIN = 1e-4f;
constexpr double SIGMA_CUT = 5.55;
constexpr int MAX_CHANNELS = 4;

inline vf splat(float x) { return vf{} + x; }
inline vi splat_i(int32_t x) { return vi{} + x; }

inline bool any(vi m) {
#if defined(__AVX512F__)
    __m512i v;
    std::memcpy(&v, &m, sizeof v);
    return _mm512_test_epi32_mask(v, v) != 0;
#elif defined(__AVX2__)
    __m256i lo, hi;
    std::memcpy(&lo, &m, sizeof lo);
    std::memcpy(&hi, reinterpret_cast<const char*>(&m) + sizeof lo, sizeof hi);
    __m256i o = _mm256_or_si256(lo, hi);
    return !_mm256_testz_si256(o, o);
#else
    int32_t r = 0;
    for (int i = 0; i < L; ++i) r |= m[i];
    return r != 0;
#endif
}

inline int count(vi m) {
    int n = 0;
    for (int i = 0; i < L; ++i) n += m[i] != 0;
    return n;
}

// exp(-s) for s >= 0 (larger s clamped at 87, where exp underflows anyway): Cephes' expf
// polynomial on the remainder after 2^n is taken out, 2^n assembled in the exponent bits.
inline vf exp_neg(vf s) {
    vf x = -(s < 87.0f ? s : splat(87.0f));
    x = x > 0.0f ? splat(0.0f) : x;
    vi n = __builtin_convertvector(x * 1.44269504088896341f - 0.5f, vi);  // round(x log2 e), x <= 0
    vf nf = __builtin_convertvector(n, vf);
    vf r = x - nf * 0.693359375f + nf * 2.12194440e-4f;
    vf p = splat(1.9875691500e-4f);
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    p = p * r * r + r + 1.0f;
    vi bits = (n + 127) << 23;
    vf scale;
    std::memcpy(&scale, &bits, sizeof scale);
    return p * scale;
}

struct Entry {
    float mx, my, a, b, c, op;
    float col[MAX_CHANNELS];
};

inline Entry entry(const float* gauss, int64_t e, int F, int D) {
    const float* g = gauss + e * F;
    Entry r{g[0], g[1], g[2], g[3], g[4], g[5], {0.0f, 0.0f, 0.0f, 0.0f}};
    for (int k = 0; k < D; ++k) r.col[k] = g[6 + k];
    return r;
}

// Rows [y0, y1) of [y_lo, y_hi) that the entry's ellipse sigma <= SIGMA_CUT reaches, as
// _row_range computes them (axis 1), and likewise its columns (axis 0).
inline void extent(const Entry& g, int axis, int lo, int hi, int* i0, int* i1) {
    double a = g.a, b = g.b, c = g.c, det = a * c - b * b;
    if (a <= 0.0 || det <= 0.0) {
        *i0 = lo;
        *i1 = hi;
        return;
    }
    double half = std::sqrt(2.0 * SIGMA_CUT * (axis == 1 ? a : c) / det) + 1e-3;
    double m = axis == 1 ? g.my : g.mx;
    int l = static_cast<int>(std::ceil(m - half - 0.5));
    int h = static_cast<int>(std::floor(m + half - 0.5)) + 1;
    *i0 = l > lo ? l : lo;
    *i1 = h < hi ? h : hi;
    if (*i1 < *i0) *i1 = *i0;
}

// The chunks of L pixels of a tile row that the entry's columns [x0, x1) touch.
inline void chunk_range(const Entry& g, int x_lo, int x_hi, int* c0, int* c1) {
    int x0, x1;
    extent(g, 0, x_lo, x_hi, &x0, &x1);
    *c0 = (x0 - x_lo) / L;
    *c1 = x1 > x0 ? (x1 - x_lo + L - 1) / L : *c0;
}

struct Shape {
    int ts, tiles_x, tiles_y, C, H, W, D, chunks;
};

struct TileBox {
    int cam, y_lo, y_hi, x_lo, x_hi;
};

inline TileBox tile_box(int64_t t, const Shape& s) {
    int64_t per_cam = static_cast<int64_t>(s.tiles_x) * s.tiles_y;
    int cam = static_cast<int>(t / per_cam), r = static_cast<int>(t % per_cam);
    int y_lo = (r / s.tiles_x) * s.ts, x_lo = (r % s.tiles_x) * s.ts;
    int y_hi = y_lo + s.ts < s.H ? y_lo + s.ts : s.H;
    int x_hi = x_lo + s.ts < s.W ? x_lo + s.ts : s.W;
    return {cam, y_lo, y_hi, x_lo, x_hi};
}

// The lanes' pixel centres minus the chunk's first pixel: 0.5, 1.5, ...
inline vf lane_centres() {
    vf v;
    for (int i = 0; i < L; ++i) v[i] = i + 0.5f;
    return v;
}

// Sigma and alpha of an entry over one chunk of a row; ok marks the lanes it composites onto.
struct Alphas {
    vf sigma, alpha, E;
    vi ok;
};

inline Alphas alphas(const Entry& g, vf dx, float dy) {
    Alphas r;
    r.sigma = 0.5f * (g.a * dx * dx + g.c * dy * dy) + g.b * dx * dy;
    r.E = exp_neg(r.sigma);
    vf alpha = g.op * r.E;
    r.alpha = alpha < ALPHA_MAX ? alpha : splat(ALPHA_MAX);
    r.ok = (r.sigma >= 0.0f) & (r.alpha >= ALPHA_MIN);
    return r;
}

// Alphas of an entry over rows [ya, yb) and chunks [ca, cb) of a tile, into per-chunk buffers
// (p = row * chunks + chunk): computed first, without branches, so the exp polynomials of
// successive rows overlap instead of waiting on the compositing's branches.
struct RowBuffers {
    std::vector<vf> alpha, E;
    std::vector<vi> ok;
    explicit RowBuffers(int P) : alpha(P), E(P), ok(P) {}
};

inline void entry_alphas(const Entry& g, const TileBox& box, int chunks, int ya, int yb, int ca,
                         int cb, vf centres, RowBuffers& out) {
    for (int y = ya; y < yb; ++y) {
        const float dy = g.my - (y + 0.5f);
        for (int ch = ca; ch < cb; ++ch) {
            const int p = (y - box.y_lo) * chunks + ch;
            Alphas al = alphas(g, g.mx - (box.x_lo + ch * L) - centres, dy);
            out.alpha[p] = al.alpha;
            out.E[p] = al.E;
            out.ok[p] = al.ok;
        }
    }
}

template <class Fn>
void parallel_tiles(int64_t n_tiles, int threads, Fn fn) {
    std::atomic<int64_t> next{0};
    auto work = [&]() {
        for (int64_t t = next.fetch_add(1); t < n_tiles; t = next.fetch_add(1)) fn(t);
    };
    int extra = threads > 1 ? threads - 1 : 0;
    if (extra > n_tiles) extra = static_cast<int>(n_tiles);
    std::vector<std::thread> pool;
    pool.reserve(extra);
    for (int i = 0; i < extra; ++i) pool.emplace_back(work);
    work();
    for (auto& th : pool) th.join();
}

void forward_tile(int64_t t, const float* gauss, int F, int64_t start, int64_t n, const Shape& s,
                  const float* bg, float* render, float* trans, int64_t* last) {
    TileBox box = tile_box(t, s);
    const int P = s.ts * s.chunks;
    std::vector<vf> T(P, splat(1.0f)), acc(P * MAX_CHANNELS, splat(0.0f));
    std::vector<vi> stop(P, splat_i(0)), done(P);
    RowBuffers rows(P);
    const vf centres = lane_centres();
    int active = 0;
    for (int r = 0; r < s.ts; ++r)
        for (int ch = 0; ch < s.chunks; ++ch) {
            vi outside;
            for (int i = 0; i < L; ++i)
                outside[i] = (box.y_lo + r >= box.y_hi || box.x_lo + ch * L + i >= box.x_hi) ? -1 : 0;
            done[r * s.chunks + ch] = outside;
            active += L - count(outside);
        }
    for (int64_t j = 0; j < n && active > 0; ++j) {
        const Entry g = entry(gauss, start + j, F, s.D);
        int ya, yb, ca, cb;
        extent(g, 1, box.y_lo, box.y_hi, &ya, &yb);
        chunk_range(g, box.x_lo, box.x_hi, &ca, &cb);
        const vi next_stop = splat_i(static_cast<int32_t>(j + 1));
        entry_alphas(g, box, s.chunks, ya, yb, ca, cb, centres, rows);
        for (int y = ya; y < yb; ++y) {
            for (int ch = ca; ch < cb; ++ch) {
                const int p = (y - box.y_lo) * s.chunks + ch;
                const vf alpha = rows.alpha[p];
                vi ok = rows.ok[p] & ~done[p];
                if (!any(ok)) continue;
                vf next_T = T[p] * (1.0f - alpha);
                vi sat = ok & (next_T <= T_MIN);
                if (any(sat)) {
                    done[p] |= sat;
                    active -= count(sat);
                    ok &= ~sat;
                }
                vf w = ok ? alpha * T[p] : splat(0.0f);
                for (int k = 0; k < s.D; ++k) acc[p * MAX_CHANNELS + k] += w * g.col[k];
                T[p] = ok ? next_T : T[p];
                stop[p] = ok ? next_stop : stop[p];
            }
        }
    }
    for (int y = box.y_lo; y < box.y_hi; ++y)
        for (int x = box.x_lo; x < box.x_hi; ++x) {
            const int p = (y - box.y_lo) * s.chunks + (x - box.x_lo) / L, i = (x - box.x_lo) % L;
            const int64_t pix = (static_cast<int64_t>(box.cam) * s.H + y) * s.W + x;
            for (int k = 0; k < s.D; ++k)
                render[pix * s.D + k] = acc[p * MAX_CHANNELS + k][i] + T[p][i] * bg[box.cam * s.D + k];
            trans[pix] = T[p][i];
            last[pix] = stop[p][i];
        }
}

// The sum of the lanes, in a fixed order.
inline double hsum(vf v) {
#if defined(__AVX512F__)
    if constexpr (L == 16) {
        __m512 m;
        std::memcpy(&m, &v, sizeof m);
        return _mm512_reduce_add_ps(m);
    }
#endif
    float r = 0.0f;
    for (int i = 0; i < L; ++i) r += v[i];
    return r;
}

void backward_tile(int64_t t, const float* gauss, int F, int64_t start, const Shape& s,
                   const float* bg, const float* trans, const int64_t* last,
                   const float* d_render, const float* d_alpha, double* grads) {
    TileBox box = tile_box(t, s);
    const int P = s.ts * s.chunks;
    std::vector<vf> T(P, splat(0.0f)), q(P, splat(0.0f));
    std::vector<vf> dC(P * MAX_CHANNELS, splat(0.0f)), buf(P * MAX_CHANNELS, splat(0.0f));
    std::vector<vi> stop(P, splat_i(0));
    int64_t walked = 0;
    for (int y = box.y_lo; y < box.y_hi; ++y)
        for (int x = box.x_lo; x < box.x_hi; ++x) {
            const int p = (y - box.y_lo) * s.chunks + (x - box.x_lo) / L, i = (x - box.x_lo) % L;
            const int64_t pix = (static_cast<int64_t>(box.cam) * s.H + y) * s.W + x;
            T[p][i] = trans[pix];
            stop[p][i] = static_cast<int32_t>(last[pix]);
            walked = last[pix] > walked ? last[pix] : walked;
            float bg_dot = 0.0f;
            for (int k = 0; k < s.D; ++k) {
                dC[p * MAX_CHANNELS + k][i] = d_render[pix * s.D + k];
                bg_dot += bg[box.cam * s.D + k] * d_render[pix * s.D + k];
            }
            q[p][i] = trans[pix] * (d_alpha[pix] - bg_dot);
        }
    const vf centres = lane_centres();
    RowBuffers rows(P);
    for (int64_t j = walked - 1; j >= 0; --j) {
        const int64_t e = start + j;
        const Entry g = entry(gauss, e, F, s.D);
        const vi jj = splat_i(static_cast<int32_t>(j));
        vf g0 = splat(0.0f), g1 = g0, g2 = g0, g3 = g0, g4 = g0, g5 = g0;
        vf h[MAX_CHANNELS] = {g0, g0, g0, g0};
        bool touched = false;
        int ya, yb, ca, cb;
        extent(g, 1, box.y_lo, box.y_hi, &ya, &yb);
        chunk_range(g, box.x_lo, box.x_hi, &ca, &cb);
        entry_alphas(g, box, s.chunks, ya, yb, ca, cb, centres, rows);
        for (int y = ya; y < yb; ++y) {
            const float dy = g.my - (y + 0.5f);
            for (int ch = ca; ch < cb; ++ch) {
                const int p = (y - box.y_lo) * s.chunks + ch;
                const vf alpha = rows.alpha[p];
                vi ok = rows.ok[p] & (jj < stop[p]);
                if (!any(ok)) continue;
                touched = true;
                vf ra = 1.0f / (1.0f - alpha);
                T[p] = ok ? T[p] * ra : T[p];  // the transmittance in front of this entry
                vf w = ok ? alpha * T[p] : splat(0.0f);
                vf v_alpha = q[p] * ra;
                for (int k = 0; k < s.D; ++k) {
                    vf d = dC[p * MAX_CHANNELS + k];
                    vf& behind = buf[p * MAX_CHANNELS + k];
                    h[k] += w * d;
                    v_alpha += (g.col[k] * T[p] - behind * ra) * d;
                    behind += g.col[k] * w;
                }
                vi shaped = ok & (alpha < ALPHA_MAX);  // a clamped alpha passes no gradient
                vf v_sigma = shaped ? -alpha * v_alpha : splat(0.0f);
                vf dx = g.mx - (box.x_lo + ch * L) - centres;
                g0 += v_sigma * (g.a * dx + g.b * dy);
                g1 += v_sigma * (g.b * dx + g.c * dy);
                g2 += 0.5f * v_sigma * dx * dx;
                g3 += v_sigma * dx * dy;
                g4 += 0.5f * v_sigma * dy * dy;
                g5 += shaped ? rows.E[p] * v_alpha : splat(0.0f);
            }
        }
        if (!touched) continue;  // no pixel reached it: its gradient stays zero
        double* out = grads + e * F;
        out[0] = hsum(g0), out[1] = hsum(g1), out[2] = hsum(g2);
        out[3] = hsum(g3), out[4] = hsum(g4), out[5] = hsum(g5);
        for (int k = 0; k < s.D; ++k) out[6 + k] = hsum(h[k]);
    }
}

Shape shape(int ts, int tiles_x, int tiles_y, int C, int H, int W, int D) {
    return {ts, tiles_x, tiles_y, C, H, W, D, (ts + L - 1) / L};
}

}  // namespace

extern "C" {

// render (C, H, W, D), trans (C, H, W) and last (C, H, W) as composite_forward fills them.
int pd_composite_forward(const float* gauss, int F, const int64_t* offsets, const int64_t* counts,
                         int64_t n_tiles, int ts, int tiles_x, int tiles_y, int C, int H, int W,
                         int D, const float* bg, float* render, float* trans, int64_t* last,
                         int threads) {
    if (D < 1 || D > MAX_CHANNELS || F != 6 + D) return 1;
    const Shape s = shape(ts, tiles_x, tiles_y, C, H, W, D);
    parallel_tiles(n_tiles, threads, [&](int64_t t) {
        forward_tile(t, gauss, F, offsets[t], counts[t], s, bg, render, trans, last);
    });
    return 0;
}

// grads (n_isects, F) per list entry, as composite_backward returns them; entries that no
// pixel reached are left as they are (the caller passes zeros).
int pd_composite_backward(const float* gauss, int F, const int64_t* offsets, int64_t n_tiles,
                          int ts, int tiles_x, int tiles_y, int C, int H, int W, int D,
                          const float* bg, const float* trans, const int64_t* last,
                          const float* d_render, const float* d_alpha, double* grads,
                          int threads) {
    if (D < 1 || D > MAX_CHANNELS || F != 6 + D) return 1;
    const Shape s = shape(ts, tiles_x, tiles_y, C, H, W, D);
    parallel_tiles(n_tiles, threads, [&](int64_t t) {
        backward_tile(t, gauss, F, offsets[t], s, bg, trans, last, d_render, d_alpha, grads);
    });
    return 0;
}

}  // extern "C"
