// The fused CPU rasterizer's kernels: forward and backward compositing (a block of 4 rows of
// L / 4 pixels at a time), tile binning, per-Gaussian gradient sums, EWA projection (L Gaussians
// at a time) and SH shading, each with the rules of its torch-op counterpart (rasterize.py,
// _tiles.py, sh.py) in float32; the mean SSIM of the fit loss with its gradient
// (paradrive/metrics.py's closed form), the rest of the fit loss, the densification's sums and
// the scene graph's placement. They match the torch operations within float32 rounding (the
// tests state the tolerances), not bit for bit.
//
// Compositing:
// The rules of _tiles.composite: per pixel, the depth-sorted entries of its tile front to back, alpha = min(0.999, opacity *
// exp(-sigma)), sigma < 0 or alpha < 1/255 skipped, a pixel stops before the entry that would
// bring its transmittance to <= 1e-4. Arithmetic is float32 in vectors of L lanes, one register
// of the machine's widest vector unit: 16 with AVX-512, 8 with AVX2, else 4 (SSE, NEON). Vectors
// wider than the unit are split by the compiler into halves spilled through the stack, which
// made every kernel 5 to 10 times slower on AVX2. exp is a polynomial with the exponent put in
// by integer arithmetic.
//
// A compositing vector is a block of VH = 4 rows of VW = L / 4 pixels: most Gaussians of a fit
// cover a few pixels each way, and a row of L pixels carries more lanes outside their ellipse.
// On AVX2, 2 x 4 blocks made the forward and backward 12-16 % faster than rows of 8 on a fit's
// lists (4 x 2 blocks: 8-13 %), and 1 x 4 blocks of 4 lanes 3-12 % faster than rows of 4; 4 x 4
// blocks of 16 lanes take 16-29 % fewer vectors than rows of 16 on the same lists. A pixel's
// arithmetic is the same in any block; the order of a per-entry gradient's sum is not.
//
// Each tile is the work of one thread, in a fixed order inside it, and the lanes of a
// per-entry gradient are summed in a fixed order, so the bytes do not depend on the number of
// threads. Threads take tiles from a shared counter. The lane count sets the order of a
// per-entry gradient's sum, so the variants built for different vector units differ in the
// last bits.
//
// Built at install (setup.py) once per instruction set, with _bindings.cpp, into the modules
// paradrive/kernels/__init__.py chooses from.

#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdint>
#include <cstring>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

#include <unistd.h>

#if defined(__AVX512F__) || defined(__AVX2__)
#include <immintrin.h>
#endif

namespace {

#if defined(__AVX512F__)
constexpr int L = 16;
#elif defined(__AVX2__)
constexpr int L = 8;
#else
constexpr int L = 4;  // a 128-bit unit (SSE, NEON): 8 lanes there ran 2.5 times slower
#endif
constexpr int VH = 4;  // a compositing vector's rows
constexpr int VW = L / VH;
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
    if constexpr (L == 16) {
        __m512i v;
        std::memcpy(&v, &m, sizeof v);
        return _mm512_test_epi32_mask(v, v) != 0;
    }
#endif
#if defined(__AVX2__)
    if constexpr (L == 8) {
        __m256i v;
        std::memcpy(&v, &m, sizeof v);
        return !_mm256_testz_si256(v, v);
    }
#endif
    int32_t r = 0;
    for (int i = 0; i < L; ++i) r |= m[i];
    return r != 0;
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

// op applied to x as the intrinsics' register type R (of the same size).
template <class R, class Op>
inline vf as_register(vf x, Op op) {
    R m;
    std::memcpy(&m, &x, sizeof m);
    m = op(m);
    std::memcpy(&x, &m, sizeof m);
    return x;
}

inline vf vsqrt(vf x) {
#if defined(__AVX512F__)
    if constexpr (L == 16) return as_register<__m512>(x, [](__m512 m) { return _mm512_sqrt_ps(m); });
#endif
#if defined(__AVX2__)
    if constexpr (L == 8) return as_register<__m256>(x, [](__m256 m) { return _mm256_sqrt_ps(m); });
#endif
    for (int i = 0; i < L; ++i) x[i] = std::sqrt(x[i]);
    return x;
}

struct Entry {
    float mx, my, a, b, c, op;
    float col[MAX_CHANNELS];
    float half_y, half_x;  // see Reach
};

// The sigma beyond which opacity * exp(-sigma) < ALPHA_MIN: log(opacity / ALPHA_MIN), at most
// SIGMA_CUT (which is that of opacity 1), widened by 0.01 (1 % in alpha, far above float32's
// rounding of sigma and of the exp polynomial). Pixels past it fail the alpha test anyway, so
// leaving their rows out changes no byte; a faint Gaussian's rows are fewer.
//
// Per row of the table, the half-extents of its ellipse sigma <= that cut in rows (y) and
// columns (x), widened a little more than _row_range's margin for the rounding (a row or column
// they add is skipped by the alpha test anyway); +inf where the conic is not positive definite
// (every row and column of a tile). Computed once per row before the tiles, not per entry.
struct Reach {
    float half_y, half_x;
};

// log(x) for x >= 1 (Cephes' logf polynomial on the mantissa; about 1e-7 relative, far inside
// the cut's margin).
inline vf log_ge1(vf x) {
    vi bits;
    std::memcpy(&bits, &x, sizeof bits);
    vi e = ((bits >> 23) & 0xff) - 126;
    bits = (bits & 0x007fffff) | 0x3f000000;  // the mantissa in [0.5, 1)
    vf m;
    std::memcpy(&m, &bits, sizeof m);
    const vi small = m < 0.707106781186547524f;
    e = small ? e - 1 : e;
    m = small ? m + m - 1.0f : m - 1.0f;
    const vf ef = __builtin_convertvector(e, vf), z = m * m;
    vf y = splat(7.0376836292e-2f);
    y = y * m - 1.1514610310e-1f;
    y = y * m + 1.1676998740e-1f;
    y = y * m - 1.2420140846e-1f;
    y = y * m + 1.4249322787e-1f;
    y = y * m - 1.6668057665e-1f;
    y = y * m + 2.0000714765e-1f;
    y = y * m - 2.4999993993e-1f;
    y = y * m + 3.3333331174e-1f;
    y = y * m * z + ef * -2.12194440e-4f - 0.5f * z;
    return m + y + ef * 0.693359375f;
}

void reach_block(const float* table, int F, int64_t rows, int64_t b, Reach* out) {
    vf a, bb, c, op;
    for (int i = 0; i < L; ++i) {
        const int64_t r = b * L + i < rows ? b * L + i : rows - 1;
        a[i] = table[r * F + 2], bb[i] = table[r * F + 3], c[i] = table[r * F + 4];
        op[i] = table[r * F + 5];
    }
    vf cut = log_ge1(op > ALPHA_MIN ? op / ALPHA_MIN : splat(1.0f)) + 0.01f;
    cut = cut < static_cast<float>(SIGMA_CUT) ? cut : splat(static_cast<float>(SIGMA_CUT));
    const vf det = a * c - bb * bb;
    const vi pd = (a > 0.0f) & (det > 0.0f);
    const vf inf = splat(__builtin_inff());
    const vf hy = pd ? vsqrt(pd ? 2.0f * cut * a / det : splat(0.0f)) * 1.0001f + 2e-3f : inf;
    const vf hx = pd ? vsqrt(pd ? 2.0f * cut * c / det : splat(0.0f)) * 1.0001f + 2e-3f : inf;
    for (int i = 0; i < L && b * L + i < rows; ++i) out[b * L + i] = {hy[i], hx[i]};
}

// Rows of the table a list walks ahead of the one it reads: they are scattered over the table,
// so they are fetched into the cache early.
constexpr int PREFETCH = 4;

inline void prefetch(const float* table, const Reach* reach, const int64_t* ids, int64_t e,
                     int F) {
    __builtin_prefetch(table + ids[e] * F);
    __builtin_prefetch(reach + ids[e]);
}

inline Entry entry(const float* table, const Reach* reach, const int64_t* ids, int64_t e, int F,
                   int D) {
    const float* g = table + ids[e] * F;
    const Reach& h = reach[ids[e]];
    Entry r{g[0], g[1], g[2], g[3], g[4], g[5], {0.0f, 0.0f, 0.0f, 0.0f}, h.half_y, h.half_x};
    for (int k = 0; k < D; ++k) r.col[k] = g[6 + k];
    return r;
}

// Rows [y0, y1) of [y_lo, y_hi) that the entry's ellipse sigma <= its cut reaches, as
// _row_range computes them for SIGMA_CUT (axis 1), and likewise its columns (axis 0).
inline void extent(const Entry& g, int axis, int lo, int hi, int* i0, int* i1) {
    const float half = axis == 1 ? g.half_y : g.half_x;
    const float m = axis == 1 ? g.my : g.mx;
    float l = std::ceil(m - half - 0.5f), h = std::floor(m + half - 0.5f) + 1.0f;
    l = l > lo ? l : static_cast<float>(lo);  // clamped before the conversion (and NaN to lo)
    h = h < hi ? h : static_cast<float>(hi);
    *i0 = l < hi ? static_cast<int>(l) : hi;
    *i1 = h > *i0 ? static_cast<int>(h) : *i0;
}

// The chunks of VW pixels of a tile row that the entry's columns [x0, x1) touch, and the bands
// of VH rows that its rows [y0, y1) touch.
inline void cell_range(const Entry& g, int lo, int hi, int axis, int* c0, int* c1) {
    const int n = axis == 1 ? VH : VW;
    int i0, i1;
    extent(g, axis, lo, hi, &i0, &i1);
    *c0 = (i0 - lo) / n;
    *c1 = i1 > i0 ? (i1 - lo + n - 1) / n : *c0;
}

// A tile's pixels in vectors: bands of VH rows, each `chunks` vectors of VW pixels across;
// vector p = band * chunks + chunk, its lane i the pixel (i / VW, i % VW) of that block.
struct Shape {
    int ts, tiles_x, tiles_y, C, H, W, D, chunks, bands;
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

// The vector and lane of pixel (y, x) of a tile.
inline void slot(const TileBox& box, const Shape& s, int y, int x, int* p, int* i) {
    *p = (y - box.y_lo) / VH * s.chunks + (x - box.x_lo) / VW;
    *i = (y - box.y_lo) % VH * VW + (x - box.x_lo) % VW;
}

// The lanes' pixel centres minus the block's first pixel: 0.5, 1.5, ... across (x) and down (y).
struct Centres {
    vf x, y;
};

inline Centres lane_centres() {
    Centres c;
    for (int i = 0; i < L; ++i) c.x[i] = i % VW + 0.5f, c.y[i] = i / VW + 0.5f;
    return c;
}

// The lanes' offsets from an entry's mean, down (dy, of a band) and across (dx, of a chunk).
inline vf lane_dy(const Entry& g, const TileBox& box, int band, const Centres& c) {
    return g.my - (static_cast<float>(box.y_lo + band * VH) + c.y);
}

inline vf lane_dx(const Entry& g, const TileBox& box, int chunk, const Centres& c) {
    return g.mx - (box.x_lo + chunk * VW) - c.x;
}

// Sigma and alpha of an entry over one block; ok marks the lanes it composites onto.
struct Alphas {
    vf sigma, alpha, E;
    vi ok;
};

inline Alphas alphas(const Entry& g, vf dx, vf dy) {
    Alphas r;
    r.sigma = 0.5f * (g.a * dx * dx + g.c * dy * dy) + g.b * dx * dy;
    r.E = exp_neg(r.sigma);
    vf alpha = g.op * r.E;
    r.alpha = alpha < ALPHA_MAX ? alpha : splat(ALPHA_MAX);
    r.ok = (r.sigma >= 0.0f) & (r.alpha >= ALPHA_MIN);
    return r;
}

// Alphas of an entry over bands [ba, bb) and chunks [ca, cb) of a tile, into per-vector
// buffers: computed first, without branches, so the exp polynomials of successive vectors
// overlap instead of waiting on the compositing's branches. An alpha is 0 where its lane does
// not composite (any other is at least ALPHA_MIN), so it carries that mask too. With E,
// exp(-sigma) as well (the backward's opacity gradient).
template <bool WITH_E>
inline void entry_alphas(const Entry& g, const TileBox& box, int chunks, int ba, int bb, int ca,
                         int cb, const Centres& centres, vf* alpha, vf* E) {
    for (int band = ba; band < bb; ++band) {
        const vf dy = lane_dy(g, box, band, centres);
        for (int ch = ca; ch < cb; ++ch) {
            const int p = band * chunks + ch;
            Alphas al = alphas(g, lane_dx(g, box, ch, centres), dy);
            alpha[p] = al.ok ? al.alpha : splat(0.0f);
            if constexpr (WITH_E) E[p] = al.E;
        }
    }
}

// Worker threads kept between calls (starting threads for every call cost tens of
// microseconds each, and a fit iteration makes about a dozen calls). One job at a time: a
// caller that finds the pool busy (another Python thread in a kernel) starts its own threads.
//
// Waking a sleeping thread through the kernel takes 30 to 80 microseconds on a virtual machine,
// longer than many of the jobs. So a worker that finished a job watches for the next one for
// SPIN before it sleeps, and the caller watches for the workers to finish for as long before it
// sleeps; a fit's calls come closer together than that, so they wake nobody.
class Pool {
  public:
    // Runs fn on the calling thread and on `extra` workers; returns when all have finished.
    bool try_run(int extra, const std::function<void()>& fn) {
        std::unique_lock<std::mutex> busy(job_mu_, std::try_to_lock);
        if (!busy.owns_lock()) return false;
        std::unique_lock<std::mutex> lk(mu_);
        for (; size_ < extra; ++size_) std::thread(&Pool::worker, this, generation_.load()).detach();
        job_ = &fn;
        taking_ = extra;
        running_ = extra;
        generation_.fetch_add(1);
        const bool sleepers = sleeping_ > 0;
        lk.unlock();
        if (sleepers) wake_.notify_all();
        fn();
        if (!spin_until([&] { return running_.load() == 0; })) {
            lk.lock();
            finished_.wait(lk, [&] { return running_.load() == 0; });
            lk.unlock();
        }
        job_ = nullptr;
        return true;
    }

  private:
    static constexpr std::chrono::microseconds SPIN{300};

    // Whether done() held within SPIN (checked between pauses).
    template <class Done>
    static bool spin_until(Done done) {
        const auto end = std::chrono::steady_clock::now() + SPIN;
        for (int i = 0;; ++i) {
            if (done()) return true;
            if ((i & 63) == 63 && std::chrono::steady_clock::now() > end) return false;
#if defined(__x86_64__) || defined(__i386__)
            __builtin_ia32_pause();
#endif
        }
    }

    void worker(uint64_t seen) {
        for (;;) {
            if (!spin_until([&] { return generation_.load() != seen; })) {
                std::unique_lock<std::mutex> lk(mu_);
                ++sleeping_;
                wake_.wait(lk, [&] { return generation_.load() != seen; });
                --sleeping_;
            }
            seen = generation_.load();
            if (taking_.fetch_sub(1) <= 0) continue;  // enough workers on this job already
            (*job_.load())();
            if (running_.fetch_sub(1) == 1) {
                std::lock_guard<std::mutex> lk(mu_);
                finished_.notify_one();
            }
        }
    }

    std::mutex job_mu_, mu_;
    std::condition_variable wake_, finished_;
    std::atomic<const std::function<void()>*> job_{nullptr};
    std::atomic<uint64_t> generation_{0};
    std::atomic<int> taking_{0}, running_{0};
    int size_ = 0, sleeping_ = 0;
};

std::atomic<Pool*> the_pool{nullptr};
std::atomic<pid_t> pool_pid{0};

// The process's pool. A forked child gets a new one: the parent's workers are not in it, and
// the state of the parent's locks and condition variables is not the child's. Pools are never
// destroyed (their detached workers outlive static teardown).
Pool& pool() {
    Pool* p = the_pool.load();
    if (p != nullptr && pool_pid.load() == getpid()) return *p;
    Pool* fresh = new Pool();
    if (the_pool.compare_exchange_strong(p, fresh)) {
        pool_pid = getpid();
        return *fresh;
    }
    delete fresh;  // another thread made this process's pool first
    return *p;
}

// fn(t) for t in [0, n_tiles) on `threads` threads, which take the next t from a shared counter.
template <class Fn>
void parallel_tiles(int64_t n_tiles, int threads, Fn fn) {
    std::atomic<int64_t> next{0};
    const std::function<void()> work = [&]() {
        for (int64_t t = next.fetch_add(1); t < n_tiles; t = next.fetch_add(1)) fn(t);
    };
    int extra = threads > 1 ? threads - 1 : 0;
    if (extra > n_tiles - 1) extra = n_tiles > 1 ? static_cast<int>(n_tiles - 1) : 0;
    if (extra == 0) {
        work();
        return;
    }
    if (pool().try_run(extra, work)) return;
    std::vector<std::thread> spawned;
    spawned.reserve(extra);
    for (int i = 0; i < extra; ++i) spawned.emplace_back(work);
    work();
    for (auto& th : spawned) th.join();
}

// The Reach of every row of the table, into out (rows of 2 floats).
const Reach* reaches(const float* table, int64_t rows, int F, float* into, int threads) {
    Reach* out = reinterpret_cast<Reach*>(into);
    const int64_t per_part = 64 * L;
    parallel_tiles((rows + per_part - 1) / per_part, threads, [&](int64_t part) {
        const int64_t b1 = ((part + 1) * per_part < rows ? (part + 1) * per_part : rows);
        for (int64_t b = part * 64; b * L < b1; ++b) reach_block(table, F, rows, b, out);
    });
    return out;
}

void forward_tile(int64_t t, const float* table, const Reach* reach, const int64_t* ids, int F,
                  int64_t start, int64_t n, const Shape& s, const float* bg, float* render,
                  float* trans, int64_t* last) {
    TileBox box = tile_box(t, s);
    const int P = s.bands * s.chunks;
    std::vector<vf> T(P, splat(1.0f)), acc(P * MAX_CHANNELS, splat(0.0f));
    std::vector<vi> stop(P, splat_i(0)), done(P);
    std::vector<vf> lane_alpha(P);
    const Centres centres = lane_centres();
    int active = 0;
    for (int band = 0; band < s.bands; ++band)
        for (int ch = 0; ch < s.chunks; ++ch) {
            vi outside;
            for (int i = 0; i < L; ++i)
                outside[i] = (box.y_lo + band * VH + i / VW >= box.y_hi
                              || box.x_lo + ch * VW + i % VW >= box.x_hi) ? -1 : 0;
            done[band * s.chunks + ch] = outside;
            active += L - count(outside);
        }
    for (int64_t j = 0; j < n && active > 0; ++j) {
        if (j + PREFETCH < n) prefetch(table, reach, ids, start + j + PREFETCH, F);
        const Entry g = entry(table, reach, ids, start + j, F, s.D);
        int ba, bb, ca, cb;
        cell_range(g, box.y_lo, box.y_hi, 1, &ba, &bb);
        cell_range(g, box.x_lo, box.x_hi, 0, &ca, &cb);
        const vi next_stop = splat_i(static_cast<int32_t>(j + 1));
        entry_alphas<false>(g, box, s.chunks, ba, bb, ca, cb, centres, lane_alpha.data(),
                            nullptr);
        for (int band = ba; band < bb; ++band) {
            for (int ch = ca; ch < cb; ++ch) {
                const int p = band * s.chunks + ch;
                const vf alpha = lane_alpha[p];
                // no branch for a vector none of whose lanes composites (its weights are 0):
                // 2 % faster than skipping it (the backward, with more work a vector, skips)
                vi ok = (alpha > 0.0f) & ~done[p];
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
            int p, i;
            slot(box, s, y, x, &p, &i);
            const int64_t pix = (static_cast<int64_t>(box.cam) * s.H + y) * s.W + x;
            for (int k = 0; k < s.D; ++k)
                render[pix * s.D + k] = acc[p * MAX_CHANNELS + k][i] + T[p][i] * bg[box.cam * s.D + k];
            trans[pix] = T[p][i];
            last[pix] = stop[p][i];
        }
}

// The sum of the lanes, in a fixed order.
inline float hsum(vf v) {
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

void backward_tile(int64_t t, const float* table, const Reach* reach, const int64_t* ids, int F,
                   int64_t start, int64_t n, const Shape& s, const float* bg, const float* trans,
                   const int64_t* last, const float* d_render, const float* d_alpha,
                   float* grads) {
    TileBox box = tile_box(t, s);
    const int P = s.bands * s.chunks;
    std::vector<vf> T(P, splat(0.0f)), q(P, splat(0.0f));
    std::vector<vf> dC(P * MAX_CHANNELS, splat(0.0f)), buf(P * MAX_CHANNELS, splat(0.0f));
    std::vector<vi> stop(P, splat_i(0));
    int64_t walked = 0;
    for (int y = box.y_lo; y < box.y_hi; ++y)
        for (int x = box.x_lo; x < box.x_hi; ++x) {
            int p, i;
            slot(box, s, y, x, &p, &i);
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
    const Centres centres = lane_centres();
    std::vector<vf> lane_alpha(P), lane_E(P);
    if (n > walked)  // entries behind every pixel's last: no gradient
        std::memset(grads + (start + walked) * F, 0, sizeof(float) * F * (n - walked));
    for (int64_t j = walked - 1; j >= 0; --j) {
        const int64_t e = start + j;
        if (j >= PREFETCH) prefetch(table, reach, ids, e - PREFETCH, F);
        const Entry g = entry(table, reach, ids, e, F, s.D);
        const vi jj = splat_i(static_cast<int32_t>(j));
        vf g0 = splat(0.0f), g1 = g0, g2 = g0, g3 = g0, g4 = g0, g5 = g0;
        vf h[MAX_CHANNELS] = {g0, g0, g0, g0};
        bool touched = false;
        int ba, bb, ca, cb;
        cell_range(g, box.y_lo, box.y_hi, 1, &ba, &bb);
        cell_range(g, box.x_lo, box.x_hi, 0, &ca, &cb);
        entry_alphas<true>(g, box, s.chunks, ba, bb, ca, cb, centres, lane_alpha.data(),
                           lane_E.data());
        for (int band = ba; band < bb; ++band) {
            const vf dy = lane_dy(g, box, band, centres);
            for (int ch = ca; ch < cb; ++ch) {
                const int p = band * s.chunks + ch;
                const vf alpha = lane_alpha[p];
                vi ok = (alpha > 0.0f) & (jj < stop[p]);
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
                const vf dx = lane_dx(g, box, ch, centres);
                g0 += v_sigma * (g.a * dx + g.b * dy);
                g1 += v_sigma * (g.b * dx + g.c * dy);
                g2 += 0.5f * v_sigma * dx * dx;
                g3 += v_sigma * dx * dy;
                g4 += 0.5f * v_sigma * dy * dy;
                g5 += shaped ? lane_E[p] * v_alpha : splat(0.0f);
            }
        }
        float* out = grads + e * F;
        if (!touched) {  // no pixel reached it
            std::memset(out, 0, sizeof(float) * F);
            continue;
        }
        out[0] = hsum(g0), out[1] = hsum(g1), out[2] = hsum(g2);
        out[3] = hsum(g3), out[4] = hsum(g4), out[5] = hsum(g5);
        for (int k = 0; k < s.D; ++k) out[6 + k] = hsum(h[k]);
    }
}

Shape shape(int ts, int tiles_x, int tiles_y, int C, int H, int W, int D) {
    return {ts, tiles_x, tiles_y, C, H, W, D, (ts + VW - 1) / VW, (ts + VH - 1) / VH};
}

// Tiles [x0, x1) x [y0, y1) of a box of half-size (rx, ry) around (mx, my), as
// _tiles.bin_gaussians computes them (the difference in float32, the division in double).
struct TileRect {
    int x0, x1, y0, y1;
};

inline int clamp_tile(double v, int n) {
    return v < 0.0 ? 0 : (v > n ? n : static_cast<int>(v));
}

inline TileRect tile_rect(const float* means2d, const float* radii, int64_t g, int ts,
                          int tiles_x, int tiles_y) {
    const float mx = means2d[2 * g], my = means2d[2 * g + 1], rx = radii[2 * g],
                ry = radii[2 * g + 1];
    return {clamp_tile(std::floor(static_cast<double>(mx - rx) / ts), tiles_x),
            clamp_tile(std::ceil(static_cast<double>(mx + rx) / ts), tiles_x),
            clamp_tile(std::floor(static_cast<double>(my - ry) / ts), tiles_y),
            clamp_tile(std::ceil(static_cast<double>(my + ry) / ts), tiles_y)};
}

// A float's bits as an unsigned key with the float's order (negatives flipped).
inline uint32_t order_key(float f) {
    uint32_t u;
    std::memcpy(&u, &f, sizeof u);
    return (u & 0x80000000u) ? ~u : (u | 0x80000000u);
}

// ---- EWA projection (rasterize._project), L Gaussians
// per vector in float32. Small matrices are arrays of 9 row-major vectors.

constexpr float RADIUS_SIGMAS = 3.33f;

// Lane i of a field of row n0 + i of a (N, stride) array; rows past N repeat the last one.
inline vf load_lanes(const float* a, int stride, int k, const int64_t* rows) {
    vf v;
    for (int i = 0; i < L; ++i) v[i] = a[rows[i] * stride + k];
    return v;
}

struct Lanes {
    int64_t rows[L];
    int valid;
};

// The rows of block b of a list of m ids (ids == nullptr: the ids 0..m-1).
inline Lanes block_rows(const int64_t* ids, int64_t m, int64_t b) {
    Lanes r;
    r.valid = 0;
    for (int i = 0; i < L; ++i) {
        int64_t j = b * L + i;
        if (j < m) r.valid = i + 1;
        j = j < m ? j : m - 1;
        r.rows[i] = ids ? ids[j] : j;
    }
    return r;
}

struct Quat {
    vf w, x, y, z, norm;  // unit quaternion and the (floored) norm it was divided by
};

inline Quat unit_quat(const float* quats, const Lanes& g) {
    vf w = load_lanes(quats, 4, 0, g.rows), x = load_lanes(quats, 4, 1, g.rows);
    vf y = load_lanes(quats, 4, 2, g.rows), z = load_lanes(quats, 4, 3, g.rows);
    vf n = vsqrt(w * w + x * x + y * y + z * z);
    n = n > 1e-12f ? n : splat(1e-12f);
    return {w / n, x / n, y / n, z / n, n};
}

inline void rotmat(const Quat& q, vf* R) {
    const vf w = q.w, x = q.x, y = q.y, z = q.z;
    R[0] = 1.0f - 2.0f * (y * y + z * z), R[1] = 2.0f * (x * y - w * z), R[2] = 2.0f * (x * z + w * y);
    R[3] = 2.0f * (x * y + w * z), R[4] = 1.0f - 2.0f * (x * x + z * z), R[5] = 2.0f * (y * z - w * x);
    R[6] = 2.0f * (x * z - w * y), R[7] = 2.0f * (y * z + w * x), R[8] = 1.0f - 2.0f * (x * x + y * y);
}

// cov3 = M M^T with M = R diag(s); M and R are returned too.
inline void covariance(const float* quats, const float* scales, const Lanes& g, vf* cov, vf* M,
                       vf* R, Quat* q) {
    *q = unit_quat(quats, g);
    rotmat(*q, R);
    for (int j = 0; j < 3; ++j) {
        const vf s = load_lanes(scales, 3, j, g.rows);
        for (int i = 0; i < 3; ++i) M[3 * i + j] = R[3 * i + j] * s;
    }
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            cov[3 * i + j] = M[3 * i] * M[3 * j] + M[3 * i + 1] * M[3 * j + 1] + M[3 * i + 2] * M[3 * j + 2];
}

// One camera's view of the lanes: camera-space mean and covariance, and the clamped Jacobian.
struct Camera {
    float Rv[9], t[3], fx, fy, cx, cy;
};

inline Camera camera(const float* viewmats, const float* Ks, int c) {
    const float* v = viewmats + 16 * c;
    const float* K = Ks + 9 * c;
    Camera r;
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) r.Rv[3 * i + j] = v[4 * i + j];
        r.t[i] = v[4 * i + 3];
    }
    r.fx = K[0], r.fy = K[4], r.cx = K[2], r.cy = K[5];
    return r;
}

struct View {
    vf mc[3], S[9], zs, tx, ty;
    vi in_depth, clx, cly;
};

inline View view(const Camera& cam, const vf* mean, const vf* cov, int width, int height,
                 float near, float far) {
    View r;
    for (int i = 0; i < 3; ++i)
        r.mc[i] = cam.Rv[3 * i] * mean[0] + cam.Rv[3 * i + 1] * mean[1] + cam.Rv[3 * i + 2] * mean[2] + cam.t[i];
    vf A[9];  // Rv cov
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            A[3 * i + j] = cam.Rv[3 * i] * cov[j] + cam.Rv[3 * i + 1] * cov[3 + j] + cam.Rv[3 * i + 2] * cov[6 + j];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            r.S[3 * i + j] = A[3 * i] * cam.Rv[3 * j] + A[3 * i + 1] * cam.Rv[3 * j + 1] + A[3 * i + 2] * cam.Rv[3 * j + 2];
    r.in_depth = (r.mc[2] > near) & (r.mc[2] < far);
    r.zs = r.in_depth ? r.mc[2] : splat(1.0f);
    const vf rx = r.mc[0] / r.zs, ry = r.mc[1] / r.zs;
    const float x_hi = (width - cam.cx) / cam.fx + 0.15f * width / cam.fx;
    const float x_lo = -(cam.cx / cam.fx + 0.15f * width / cam.fx);
    const float y_hi = (height - cam.cy) / cam.fy + 0.15f * height / cam.fy;
    const float y_lo = -(cam.cy / cam.fy + 0.15f * height / cam.fy);
    r.tx = rx < x_hi ? rx : splat(x_hi);
    r.tx = r.tx > x_lo ? r.tx : splat(x_lo);
    r.ty = ry < y_hi ? ry : splat(y_hi);
    r.ty = r.ty > y_lo ? r.ty : splat(y_lo);
    r.clx = r.tx != rx;
    r.cly = r.ty != ry;
    return r;
}

// (c00, c11, c01) of J S J^T, J = [[j00, 0, j02], [0, j11, j12]].
inline void cov2(const vf* S, vf j00, vf j02, vf j11, vf j12, vf* c) {
    c[0] = j00 * j00 * S[0] + 2.0f * j00 * j02 * S[2] + j02 * j02 * S[8];
    c[1] = j11 * j11 * S[4] + 2.0f * j11 * j12 * S[5] + j12 * j12 * S[8];
    c[2] = j00 * j11 * S[1] + j00 * j12 * S[2] + j02 * j11 * S[5] + j02 * j12 * S[8];
}

inline vf ceil_pos(vf x) {  // ceil of x >= 0, capped at 1e9
    x = x < 1e9f ? x : splat(1e9f);
    vf t = __builtin_convertvector(__builtin_convertvector(x, vi), vf);
    return t < x ? t + 1.0f : t;
}

struct ProjectArgs {
    const float *means, *quats, *scales, *opacities, *viewmats, *Ks;
    int64_t N;
    int C, width, height;
    float near, far, eps2d, radius_clip;
};

// Rows of the compositing table (C*N, F) the projection fills besides its own outputs: the
// mean, the conic and the opacity in columns 0..5, and the depth in column depth_col (none if
// < 0); the colours are the SH kernel's.
struct TableOut {
    float* rows;
    int F, depth_col;
};

void project_block(const ProjectArgs& a, int64_t b, float* means2d, float* conics, float* depths,
                   int32_t* radii, const TableOut& table) {
    const Lanes g = block_rows(nullptr, a.N, b);
    vf cov[9], M[9], R[9], mean[3];
    Quat q;
    covariance(a.quats, a.scales, g, cov, M, R, &q);
    for (int k = 0; k < 3; ++k) mean[k] = load_lanes(a.means, 3, k, g.rows);
    const vf op = load_lanes(a.opacities, 1, 0, g.rows);
    vf extend;
    for (int i = 0; i < L; ++i) {
        const float ratio = op[i] / ALPHA_MIN > 1.0f ? op[i] / ALPHA_MIN : 1.0f;
        const float e = std::sqrt(2.0f * std::log(ratio));
        extend[i] = e < RADIUS_SIGMAS ? e : RADIUS_SIGMAS;
    }
    for (int c = 0; c < a.C; ++c) {
        const Camera cam = camera(a.viewmats, a.Ks, c);
        const View v = view(cam, mean, cov, a.width, a.height, a.near, a.far);
        vf c2[3];
        cov2(v.S, cam.fx / v.zs, -cam.fx * v.tx / v.zs, cam.fy / v.zs, -cam.fy * v.ty / v.zs, c2);
        const vf c00 = c2[0] + a.eps2d, c11 = c2[1] + a.eps2d, c01 = c2[2];
        const vf det = c00 * c11 - c01 * c01;
        const vf d = det > 1e-10f ? det : splat(1e-10f);
        const vf u = cam.fx * v.mc[0] / v.zs + cam.cx, w = cam.fy * v.mc[1] / v.zs + cam.cy;
        const vf rx = ceil_pos(extend * vsqrt(c00 > 0.0f ? c00 : splat(0.0f))),
                 ry = ceil_pos(extend * vsqrt(c11 > 0.0f ? c11 : splat(0.0f)));
        const vi ok = v.in_depth & (det > 0.0f) & (op >= ALPHA_MIN) & (rx > 0.0f) & (ry > 0.0f) &
                      ~((rx <= a.radius_clip) & (ry <= a.radius_clip)) & (u + rx > 0.0f) &
                      (u - rx < static_cast<float>(a.width)) & (w + ry > 0.0f) &
                      (w - ry < static_cast<float>(a.height));
        const vf conic0 = c11 / d, conic1 = -c01 / d, conic2 = c00 / d;
        for (int i = 0; i < g.valid; ++i) {
            const int64_t o = c * a.N + b * L + i;
            means2d[2 * o] = u[i], means2d[2 * o + 1] = w[i];
            conics[3 * o] = conic0[i], conics[3 * o + 1] = conic1[i], conics[3 * o + 2] = conic2[i];
            depths[o] = v.mc[2][i];
            radii[2 * o] = ok[i] ? static_cast<int32_t>(rx[i]) : 0;
            radii[2 * o + 1] = ok[i] ? static_cast<int32_t>(ry[i]) : 0;
            if (table.rows == nullptr) continue;
            float* row = table.rows + o * table.F;
            row[0] = u[i], row[1] = w[i], row[2] = conic0[i], row[3] = conic1[i];
            row[4] = conic2[i], row[5] = op[i];
            if (table.depth_col >= 0) row[table.depth_col] = v.mc[2][i];
        }
    }
}

// The gradients of the projection's outputs, row o = camera * N + Gaussian at o * stride of
// each: (C, N, 2), (C, N, 3) and (C, N) arrays, or columns of one (C*N, F) table.
struct ProjectGrads {
    const float *v2d, *v_conic, *v_depth;
    int s2d, s_conic, s_depth;
};

// Whether row o of the projection's output gradients is not all zero.
inline bool gets_gradient(const ProjectGrads& v, int64_t o) {
    const float *p = v.v2d + o * v.s2d, *q = v.v_conic + o * v.s_conic;
    return p[0] != 0.0f || p[1] != 0.0f || q[0] != 0.0f || q[1] != 0.0f || q[2] != 0.0f ||
           v.v_depth[o * v.s_depth] != 0.0f;
}

// Lanes where a camera passes a gradient.
inline vi has_gradient(const ProjectGrads& v, int64_t N, int c, const Lanes& g) {
    vi r = splat_i(0);
    for (int i = 0; i < L; ++i) r[i] = gets_gradient(v, c * N + g.rows[i]) ? -1 : 0;
    return r;
}

// Field k of camera c's rows of a (C, N, stride) array, for the lanes' Gaussians.
inline vf lane_field(const float* a, int stride, int k, int64_t N, int c, const Lanes& g) {
    return load_lanes(a + c * N * stride, stride, k, g.rows);
}

// Gradients of the lanes listed in block b of ids (Gaussians some camera passes a gradient to):
// cameras summed in order.
void project_backward_block(const ProjectArgs& a, const int64_t* ids, int64_t m, int64_t b,
                            const ProjectGrads& vg, float* v_means, float* v_quats,
                            float* v_scales) {
    const Lanes g = block_rows(ids, m, b);
    vf cov[9], M[9], R[9], mean[3];
    Quat q;
    covariance(a.quats, a.scales, g, cov, M, R, &q);
    for (int k = 0; k < 3; ++k) mean[k] = load_lanes(a.means, 3, k, g.rows);
    const vf zero = splat(0.0f);
    vf vm[3] = {zero, zero, zero};
    vf vc[9];
    for (auto& x : vc) x = zero;
    for (int c = 0; c < a.C; ++c) {
        const vi used = has_gradient(vg, a.N, c, g);
        if (!any(used)) continue;
        const Camera cam = camera(a.viewmats, a.Ks, c);
        const View v = view(cam, mean, cov, a.width, a.height, a.near, a.far);
        const float fx = cam.fx, fy = cam.fy;
        const vf r00 = fx / v.zs, r02 = -fx * v.tx / v.zs, r11 = fy / v.zs, r12 = -fy * v.ty / v.zs;
        vf c2[3];
        cov2(v.S, r00, r02, r11, r12, c2);
        // the conic's gradient back to J S J^T (c00 and c11 with eps2d)
        const vf c00 = c2[0] + a.eps2d, c11 = c2[1] + a.eps2d, c01 = c2[2];
        const vf det = c00 * c11 - c01 * c01;
        const vf d = det > 1e-10f ? det : splat(1e-10f);
        const vf va = lane_field(vg.v_conic, vg.s_conic, 0, a.N, c, g),
                 vb = lane_field(vg.v_conic, vg.s_conic, 1, a.N, c, g),
                 vcn = lane_field(vg.v_conic, vg.s_conic, 2, a.N, c, g);
        vf g00 = vcn / d, g11 = va / d, g01 = -vb / d;
        const vf v_d = (det > 1e-10f) ? -(va * c11 - vb * c01 + vcn * c00) / (d * d) : zero;
        g00 += v_d * c11;
        g11 += v_d * c00;
        g01 = 0.5f * (g01 - 2.0f * v_d * c01);
        // v_S = J^T G J, J rows r0 = (r00, 0, r02), r1 = (0, r11, r12)
        const vf r0[3] = {r00, zero, r02}, r1[3] = {zero, r11, r12};
        vf vS[9];
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                vS[3 * i + j] = g00 * r0[i] * r0[j] + g01 * (r0[i] * r1[j] + r1[i] * r0[j]) +
                                g11 * r1[i] * r1[j];
        vf u0[3], u1[3];  // S r0, S r1
        for (int i = 0; i < 3; ++i) {
            u0[i] = v.S[3 * i] * r00 + v.S[3 * i + 2] * r02;
            u1[i] = v.S[3 * i + 1] * r11 + v.S[3 * i + 2] * r12;
        }
        const vf vj00 = 2.0f * (g00 * u0[0] + g01 * u1[0]), vj02 = 2.0f * (g00 * u0[2] + g01 * u1[2]);
        const vf vj11 = 2.0f * (g01 * u0[1] + g11 * u1[1]), vj12 = 2.0f * (g01 * u0[2] + g11 * u1[2]);
        const vf z2 = v.zs * v.zs;
        const vf v2x = lane_field(vg.v2d, vg.s2d, 0, a.N, c, g),
                 v2y = lane_field(vg.v2d, vg.s2d, 1, a.N, c, g);
        vf v_x = v2x * fx / v.zs, v_y = v2y * fy / v.zs;
        vf v_zs = -(v2x * fx * v.mc[0] + v2y * fy * v.mc[1]) / z2;
        v_zs += (-vj00 * fx - vj11 * fy + vj02 * fx * v.tx + vj12 * fy * v.ty) / z2;
        v_x = v.clx ? v_x : v_x - vj02 * fx / z2;  // tx = x / zs where not clamped
        v_zs = v.clx ? v_zs : v_zs + vj02 * fx * v.tx / z2;
        v_y = v.cly ? v_y : v_y - vj12 * fy / z2;
        v_zs = v.cly ? v_zs : v_zs + vj12 * fy * v.ty / z2;
        const vf v_z = lane_field(vg.v_depth, vg.s_depth, 0, a.N, c, g) + (v.in_depth ? v_zs : zero);
        const vf vmc[3] = {v_x, v_y, v_z};
        const float* Rv = cam.Rv;
        for (int k = 0; k < 3; ++k)  // Rv^T vmc
            vm[k] += used ? Rv[k] * vmc[0] + Rv[3 + k] * vmc[1] + Rv[6 + k] * vmc[2] : zero;
        vf B[9];  // v_S Rv
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                B[3 * i + j] = vS[3 * i] * Rv[j] + vS[3 * i + 1] * Rv[3 + j] + vS[3 * i + 2] * Rv[6 + j];
        for (int i = 0; i < 3; ++i)  // Rv^T B
            for (int j = 0; j < 3; ++j)
                vc[3 * i + j] += used ? Rv[i] * B[j] + Rv[3 + i] * B[3 + j] + Rv[6 + i] * B[6 + j] : zero;
    }
    vf vs[9], vM[9], vR[9], vsc[3];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) vs[3 * i + j] = vc[3 * i + j] + vc[3 * j + i];
    for (int i = 0; i < 3; ++i)  // d(M M^T) = (V + V^T) M
        for (int j = 0; j < 3; ++j)
            vM[3 * i + j] = vs[3 * i] * M[j] + vs[3 * i + 1] * M[3 + j] + vs[3 * i + 2] * M[6 + j];
    for (int j = 0; j < 3; ++j) {
        const vf s = load_lanes(a.scales, 3, j, g.rows);
        vsc[j] = vM[j] * R[j] + vM[3 + j] * R[3 + j] + vM[6 + j] * R[6 + j];
        for (int i = 0; i < 3; ++i) vR[3 * i + j] = vM[3 * i + j] * s;
    }
    const vf w = q.w, x = q.x, y = q.y, z = q.z;
    const vf g0 = 2.0f * (-z * vR[1] + y * vR[2] + z * vR[3] - x * vR[5] - y * vR[6] + x * vR[7]);
    const vf g1 = 2.0f * (y * vR[1] + z * vR[2] + y * vR[3] - 2.0f * x * vR[4] - w * vR[5] +
                          z * vR[6] + w * vR[7] - 2.0f * x * vR[8]);
    const vf g2 = 2.0f * (-2.0f * y * vR[0] + x * vR[1] + w * vR[2] + x * vR[3] + z * vR[5] -
                          w * vR[6] + z * vR[7] - 2.0f * y * vR[8]);
    const vf g3 = 2.0f * (-2.0f * z * vR[0] - w * vR[1] + x * vR[2] + w * vR[3] - 2.0f * z * vR[4] +
                          y * vR[5] + x * vR[6] + y * vR[7]);
    // through q / max(|q|, 1e-12): the floor passes no gradient to the norm
    const vf dot = q.norm > 1e-12f ? w * g0 + x * g1 + y * g2 + z * g3 : zero;
    const vf vq[4] = {(g0 - w * dot) / q.norm, (g1 - x * dot) / q.norm, (g2 - y * dot) / q.norm,
                      (g3 - z * dot) / q.norm};
    for (int i = 0; i < g.valid; ++i) {
        const int64_t n = g.rows[i];
        for (int k = 0; k < 3; ++k) v_means[3 * n + k] = vm[k][i], v_scales[3 * n + k] = vsc[k][i];
        for (int k = 0; k < 4; ++k) v_quats[4 * n + k] = vq[k][i];
    }
}

// ---- View-dependent colour from spherical harmonics (sh.eval_sh), one Gaussian at a
// time in float32. The coefficients come in the fit's two parts: c0 (N, 1, 3) and cN (N, KN, 3)
// holding bands 1..3 (KN = K - 1).

constexpr float SH_C0 = 0.28209479177387814f, SH_C1 = 0.4886025119029199f;
constexpr float SH_C2[5] = {1.0925484305920792f, -1.0925484305920792f, 0.31539156525252005f,
                            -1.0925484305920792f, 0.5462742152960396f};
constexpr float SH_C3[7] = {-0.5900435899266435f, 2.890611442640554f, -0.4570457994644658f,
                            0.3731763325901154f, -0.4570457994644658f, 1.445305721320277f,
                            -0.5900435899266435f};
constexpr int64_t SH_CHUNK = 256;  // Gaussians a thread takes at a time

inline int sh_basis(int degree, float x, float y, float z, float* b) {
    b[0] = SH_C0;
    if (degree < 1) return 1;
    b[1] = -SH_C1 * y, b[2] = SH_C1 * z, b[3] = -SH_C1 * x;
    if (degree < 2) return 4;
    const float xx = x * x, yy = y * y, zz = z * z;
    b[4] = SH_C2[0] * x * y, b[5] = SH_C2[1] * y * z, b[6] = SH_C2[2] * (2 * zz - xx - yy);
    b[7] = SH_C2[3] * x * z, b[8] = SH_C2[4] * (xx - yy);
    if (degree < 3) return 9;
    b[9] = SH_C3[0] * y * (3 * xx - yy), b[10] = SH_C3[1] * x * y * z;
    b[11] = SH_C3[2] * y * (4 * zz - xx - yy), b[12] = SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy);
    b[13] = SH_C3[4] * x * (4 * zz - xx - yy), b[14] = SH_C3[5] * z * (xx - yy);
    b[15] = SH_C3[6] * x * (xx - 3 * yy);
    return 16;
}

// Gradient of sum_k w[k] b_k with respect to the unit direction.
inline void sh_basis_vjp(int degree, float x, float y, float z, const float* w, float* g) {
    float gx = 0, gy = 0, gz = 0;
    if (degree >= 1) gx = -SH_C1 * w[3], gy = -SH_C1 * w[1], gz = SH_C1 * w[2];
    if (degree >= 2) {
        gx += SH_C2[0] * y * w[4] - 2 * SH_C2[2] * x * w[6] + SH_C2[3] * z * w[7] + 2 * SH_C2[4] * x * w[8];
        gy += SH_C2[0] * x * w[4] + SH_C2[1] * z * w[5] - 2 * SH_C2[2] * y * w[6] - 2 * SH_C2[4] * y * w[8];
        gz += SH_C2[1] * y * w[5] + 4 * SH_C2[2] * z * w[6] + SH_C2[3] * x * w[7];
    }
    if (degree >= 3) {
        const float xx = x * x, yy = y * y, zz = z * z;
        gx += 6 * SH_C3[0] * x * y * w[9] + SH_C3[1] * y * z * w[10] - 2 * SH_C3[2] * x * y * w[11] -
              6 * SH_C3[3] * x * z * w[12] + SH_C3[4] * (4 * zz - 3 * xx - yy) * w[13] +
              2 * SH_C3[5] * x * z * w[14] + 3 * SH_C3[6] * (xx - yy) * w[15];
        gy += 3 * SH_C3[0] * (xx - yy) * w[9] + SH_C3[1] * x * z * w[10] +
              SH_C3[2] * (4 * zz - xx - 3 * yy) * w[11] - 6 * SH_C3[3] * y * z * w[12] -
              2 * SH_C3[4] * x * y * w[13] - 2 * SH_C3[5] * y * z * w[14] - 6 * SH_C3[6] * x * y * w[15];
        gz += SH_C3[1] * x * y * w[10] + 8 * SH_C3[2] * y * z * w[11] +
              SH_C3[3] * (6 * zz - 3 * xx - 3 * yy) * w[12] + 8 * SH_C3[4] * x * z * w[13] +
              SH_C3[5] * (xx - yy) * w[14];
    }
    g[0] = gx, g[1] = gy, g[2] = gz;
}

// Unit direction from the camera centre to the mean (norm floored at 1e-12); returns the norm.
inline float sh_dir(const float* mean, const float* campos, float* d) {
    const float dx = mean[0] - campos[0], dy = mean[1] - campos[1], dz = mean[2] - campos[2];
    float norm = std::sqrt(dx * dx + dy * dy + dz * dz);
    norm = norm > 1e-12f ? norm : 1e-12f;
    d[0] = dx / norm, d[1] = dy / norm, d[2] = dz / norm;
    return norm;
}


}  // namespace

extern "C" {

// The float32 lanes of the kernels' vectors (one register of the vector unit built for).
int pd_lanes() { return L; }

// render (C, H, W, D), trans (C, H, W) and last (C, H, W) as composite_forward fills them;
// list entry e is row ids[e] of table (C*N, 6 + D); reach_out (C*N, 2) gets each row's Reach,
// which the backward takes.
int pd_composite_forward(const float* table, int64_t rows, int F, const int64_t* ids,
                         const int64_t* offsets, const int64_t* counts, int64_t n_tiles, int ts,
                         int tiles_x, int tiles_y, int C, int H, int W, int D, const float* bg,
                         float* render, float* trans, int64_t* last, float* reach_out,
                         int threads) {
    if (D < 1 || D > MAX_CHANNELS || F != 6 + D) return 1;
    const Shape s = shape(ts, tiles_x, tiles_y, C, H, W, D);
    const Reach* reach = reaches(table, rows, F, reach_out, threads);
    parallel_tiles(n_tiles, threads, [&](int64_t t) {
        forward_tile(t, table, reach, ids, F, offsets[t], counts[t], s, bg, render, trans, last);
    });
    return 0;
}

// grads (n_isects, F) per list entry, as composite_backward returns them (every row written:
// zeros where no pixel reached the entry); reach_in as the forward filled it.
int pd_composite_backward(const float* table, int64_t rows, int F, const int64_t* ids,
                          const int64_t* offsets, const int64_t* counts, int64_t n_tiles, int ts,
                          int tiles_x, int tiles_y, int C, int H, int W, int D, const float* bg,
                          const float* trans, const int64_t* last, const float* d_render,
                          const float* d_alpha, const float* reach_in, float* grads,
                          int threads) {
    if (D < 1 || D > MAX_CHANNELS || F != 6 + D) return 1;
    const Shape s = shape(ts, tiles_x, tiles_y, C, H, W, D);
    const Reach* reach = reinterpret_cast<const Reach*>(reach_in);
    parallel_tiles(n_tiles, threads, [&](int64_t t) {
        backward_tile(t, table, reach, ids, F, offsets[t], counts[t], s, bg, trans, last,
                      d_render, d_alpha, grads);
    });
    return 0;
}

// First half of the tile binning. order (n,) gets the flat ids of the visible Gaussians (both
// radii > 0) sorted front to back by depth, ties by id (a stable radix sort on the float bits);
// counts (n_tiles,) gets each tile's list length. Returns the number of visible Gaussians.
int64_t pd_bin_count(const float* depths, const float* means2d, const float* radii, int64_t n,
                     int64_t n_per_cam, int ts, int tiles_x, int tiles_y, int64_t* order,
                     int64_t* counts) {
    const int64_t per_cam_tiles = static_cast<int64_t>(tiles_x) * tiles_y;
    std::vector<uint32_t> keys;
    std::vector<int64_t> idx;
    keys.reserve(static_cast<size_t>(n));
    idx.reserve(static_cast<size_t>(n));
    for (int64_t cam = 0, g = 0; g < n; ++cam)
        for (int64_t i = 0; i < n_per_cam && g < n; ++i, ++g) {
            if (!(radii[2 * g] > 0.0f && radii[2 * g + 1] > 0.0f)) continue;
            const TileRect r = tile_rect(means2d, radii, g, ts, tiles_x, tiles_y);
            const int64_t base = cam * per_cam_tiles;
            for (int ty = r.y0; ty < r.y1; ++ty)
                for (int tx = r.x0; tx < r.x1; ++tx)
                    ++counts[base + static_cast<int64_t>(ty) * tiles_x + tx];
            keys.push_back(order_key(depths[g]));
            idx.push_back(g);
        }
    const int64_t m = static_cast<int64_t>(idx.size());
    std::vector<uint32_t> keys2(m);
    std::vector<int64_t> idx2(m);
    for (int shift = 0; shift < 32; shift += 8) {  // least significant byte first: stable
        int64_t pos[257] = {0};
        for (int64_t i = 0; i < m; ++i) ++pos[((keys[i] >> shift) & 255u) + 1];
        if (m == 0 || pos[((keys[0] >> shift) & 255u) + 1] == m) continue;  // one value: as is
        for (int b = 0; b < 256; ++b) pos[b + 1] += pos[b];
        for (int64_t i = 0; i < m; ++i) {
            const int64_t k = pos[(keys[i] >> shift) & 255u]++;
            keys2[k] = keys[i];
            idx2[k] = idx[i];
        }
        keys.swap(keys2);
        idx.swap(idx2);
    }
    std::memcpy(order, idx.data(), static_cast<size_t>(m) * sizeof(int64_t));
    return m;
}

// Second half: ids (n_isects,) grouped by tile in the order of order (m,); fill (n_tiles,)
// starts as the tiles' offsets and is advanced in place.
void pd_bin_fill(const int64_t* order, int64_t m, const float* means2d, const float* radii,
                 int64_t n_per_cam, int ts, int tiles_x, int tiles_y, int64_t* fill,
                 int64_t* ids) {
    const int64_t per_cam_tiles = static_cast<int64_t>(tiles_x) * tiles_y;
    for (int64_t i = 0; i < m; ++i) {
        const int64_t g = order[i];
        const TileRect r = tile_rect(means2d, radii, g, ts, tiles_x, tiles_y);
        const int64_t base = (n_per_cam > g ? 0 : g / n_per_cam) * per_cam_tiles;
        for (int ty = r.y0; ty < r.y1; ++ty)
            for (int tx = r.x0; tx < r.x1; ++tx)
                ids[fill[base + static_cast<int64_t>(ty) * tiles_x + tx]++] = g;
    }
}

// out (n, F) float32: the rows of grads (n_isects, F) summed per Gaussian id, in list order and
// in double. Each thread owns a range of ids and walks the
// whole list, so the sums do not depend on the thread count.
void pd_sum_by_gaussian(const float* grads, const int64_t* ids, int64_t n_isects, int F,
                        int64_t n, float* out, int threads) {
    const int64_t parts = threads > 1 ? threads : 1;
    parallel_tiles(parts, threads, [&](int64_t part) {
        const int64_t lo = n * part / parts, hi = n * (part + 1) / parts;
        std::vector<double> acc(static_cast<size_t>((hi - lo) * F), 0.0);
        for (int64_t e = 0; e < n_isects; ++e) {
            const int64_t g = ids[e];
            if (g < lo || g >= hi) continue;
            double* a = acc.data() + (g - lo) * F;
            const float* v = grads + e * F;
            for (int k = 0; k < F; ++k) a[k] += v[k];
        }
        for (int64_t i = 0; i < (hi - lo) * F; ++i) out[lo * F + i] = static_cast<float>(acc[i]);
    });
}

// The densification's statistics (strategy.update_state) from the projected means' gradients
// (C, N, 2), row o = camera * N + Gaussian at o * stride: for the Gaussians a camera draws
// (radii (C, N) > 0), grad2d[n] += the norm of (g_x * sx, g_y * sy) and count[n] += 1, the
// cameras summed in order first.
void pd_grad_norms(const float* grads, int64_t stride, int C, int64_t N, float sx, float sy,
                   const int32_t* radii, float* grad2d, float* count, int threads) {
    const int64_t chunk = 4096;
    parallel_tiles((N + chunk - 1) / chunk, threads, [&](int64_t part) {
        const int64_t hi = (part + 1) * chunk < N ? (part + 1) * chunk : N;
        for (int64_t n = part * chunk; n < hi; ++n) {
            float norms = 0.0f, seen = 0.0f;
            for (int c = 0; c < C; ++c) {
                const int64_t o = c * N + n;
                if (radii[o] <= 0) continue;
                const float x = grads[o * stride] * sx, y = grads[o * stride + 1] * sy;
                norms += std::sqrt(x * x + y * y);
                seen += 1.0f;
            }
            grad2d[n] += norms;
            count[n] += seen;
        }
    });
}

}  // extern "C"

extern "C" {

// Blocks of L Gaussians a projection task takes at a time: one block a task (a shared counter
// bumped every ~100 ns, and neighbouring output rows written by both threads) left the
// projection as slow on two threads as on one.
constexpr int64_t BLOCKS_PER_TASK = 64;

// means2d (C, N, 2), conics (C, N, 3), depths (C, N) and radii (C, N, 2) as
// rasterize._project computes them, in float32; and, when table is not null, columns
// 0..5 and depth_col (if >= 0) of the compositing table (C*N, F) (see TableOut).
void pd_project_forward(const float* means, const float* quats, const float* scales,
                        const float* opacities, const float* viewmats, const float* Ks, int64_t N,
                        int C, int width, int height, float near, float far, float eps2d,
                        float radius_clip, float* means2d, float* conics, float* depths,
                        int32_t* radii, float* table, int F, int depth_col, int threads) {
    const ProjectArgs a{means, quats, scales, opacities, viewmats, Ks, N, C, width, height,
                        near, far, eps2d, radius_clip};
    const TableOut out{table, F, depth_col};
    const int64_t blocks = (N + L - 1) / L;
    parallel_tiles((blocks + BLOCKS_PER_TASK - 1) / BLOCKS_PER_TASK, threads, [&](int64_t t) {
        const int64_t hi = (t + 1) * BLOCKS_PER_TASK < blocks ? (t + 1) * BLOCKS_PER_TASK : blocks;
        for (int64_t b = t * BLOCKS_PER_TASK; b < hi; ++b)
            project_block(a, b, means2d, conics, depths, radii, out);
    });
}

// v_means (N, 3), v_quats (N, 4), v_scales (N, 3), zero-filled by the caller, get the gradients
// of the Gaussians some camera passes a gradient to (v_means2d (C, N, 2), v_conics (C, N, 3),
// v_depths (C, N), row o of each at o * its stride): the backward of rasterize._project.
void pd_project_backward(const float* means, const float* quats, const float* scales,
                         const float* viewmats, const float* Ks, int64_t N, int C, int width,
                         int height, float near, float far, float eps2d, const float* v2d,
                         int s2d, const float* v_conic, int s_conic, const float* v_depth,
                         int s_depth, float* v_means, float* v_quats, float* v_scales,
                         int threads) {
    const ProjectArgs a{means, quats, scales, nullptr, viewmats, Ks, N, C, width, height,
                        near, far, eps2d, 0.0f};
    const ProjectGrads vg{v2d, v_conic, v_depth, s2d, s_conic, s_depth};
    // Gaussians in ranges of a task's blocks; each task lists those of its range some camera
    // passes a gradient to and takes them L at a time (each lane's result is its own).
    const int64_t per_task = BLOCKS_PER_TASK * L;
    parallel_tiles((N + per_task - 1) / per_task, threads, [&](int64_t t) {
        int64_t ids[BLOCKS_PER_TASK * L], m = 0;
        const int64_t hi = (t + 1) * per_task < N ? (t + 1) * per_task : N;
        for (int64_t n = t * per_task; n < hi; ++n)
            for (int c = 0; c < C; ++c)
                if (gets_gradient(vg, c * N + n)) {
                    ids[m++] = n;
                    break;
                }
        for (int64_t b = 0; b * L < m; ++b)
            project_backward_block(a, ids, m, b, vg, v_means, v_quats, v_scales);
    });
}

}  // extern "C"

extern "C" {

// colors (C, N, 3) = max(SH + 0.5, 0) where visible (C, N) is set, 0 elsewhere; row o of
// colors at o * stride (3, or a table's row length).
void pd_sh_forward(int degree, const float* means, const float* c0, const float* cN, int KN,
                   const float* campos, int64_t N, int C, const uint8_t* visible, float* colors,
                   int stride, int threads) {
    parallel_tiles((N + SH_CHUNK - 1) / SH_CHUNK, threads, [&](int64_t chunk) {
        float b[16], d[3];
        const int64_t hi = (chunk + 1) * SH_CHUNK < N ? (chunk + 1) * SH_CHUNK : N;
        for (int64_t n = chunk * SH_CHUNK; n < hi; ++n)
            for (int c = 0; c < C; ++c) {
                float* out = colors + (c * N + n) * stride;
                if (!visible[c * N + n]) {
                    out[0] = out[1] = out[2] = 0.0f;
                    continue;
                }
                sh_dir(means + 3 * n, campos + 3 * c, d);
                const int nb = sh_basis(degree, d[0], d[1], d[2], b);
                const float* q0 = c0 + 3 * n;
                const float* qN = cN + n * KN * 3 - 3;  // row k of band 1..3 at qN + 3 k
                float v[3] = {0.5f + b[0] * q0[0], 0.5f + b[0] * q0[1], 0.5f + b[0] * q0[2]};
                for (int k = 1; k < nb; ++k)
                    for (int ch = 0; ch < 3; ++ch) v[ch] += b[k] * qN[3 * k + ch];
                for (int ch = 0; ch < 3; ++ch) out[ch] = v[ch] > 0.0f ? v[ch] : 0.0f;
            }
    });
}

// v_means (N, 3), v_c0 (N, 1, 3) and v_cN (N, KN, 3) are filled with the gradients from
// v_colors (C, N, 3) (every row written, zero where no camera passes one); colors are the
// forward's (the clamp at 0 passes none). Row o of colors is at o * s_colors, of v_colors at
// o * s_v.
void pd_sh_backward(int degree, const float* means, const float* c0, const float* cN, int KN,
                    const float* campos, int64_t N, int C, const float* colors, int s_colors,
                    const float* v_colors, int s_v, float* v_means, float* v_c0, float* v_cN,
                    int threads) {
    parallel_tiles((N + SH_CHUNK - 1) / SH_CHUNK, threads, [&](int64_t chunk) {
        float b[16], w[16], d[3], g[3];
        const int64_t hi = (chunk + 1) * SH_CHUNK < N ? (chunk + 1) * SH_CHUNK : N;
        const int64_t lo = chunk * SH_CHUNK;
        std::memset(v_means + 3 * lo, 0, sizeof(float) * 3 * (hi - lo));
        std::memset(v_c0 + 3 * lo, 0, sizeof(float) * 3 * (hi - lo));
        for (int64_t n = lo; n < hi; ++n) {
            // zeroed here, not with the chunk: the row is in the cache for the sums below, so
            // the largest gradient (N * KN * 3 floats) goes to memory once
            std::memset(v_cN + n * KN * 3, 0, sizeof(float) * KN * 3);
            for (int c = 0; c < C; ++c) {
                const float* vc = v_colors + (c * N + n) * s_v;
                if (vc[0] == 0.0f && vc[1] == 0.0f && vc[2] == 0.0f) continue;  // outside the view
                const float* col = colors + (c * N + n) * s_colors;
                const float gc[3] = {col[0] > 0.0f ? vc[0] : 0.0f, col[1] > 0.0f ? vc[1] : 0.0f,
                                     col[2] > 0.0f ? vc[2] : 0.0f};
                const float norm = sh_dir(means + 3 * n, campos + 3 * c, d);
                const int nb = sh_basis(degree, d[0], d[1], d[2], b);
                const float* q0 = c0 + 3 * n;
                const float* qN = cN + n * KN * 3 - 3;  // row k of band 1..3 at qN + 3 k
                float* v0 = v_c0 + 3 * n;
                float* vN = v_cN + n * KN * 3 - 3;
                w[0] = q0[0] * gc[0] + q0[1] * gc[1] + q0[2] * gc[2];
                for (int ch = 0; ch < 3; ++ch) v0[ch] += b[0] * gc[ch];
                for (int k = 1; k < nb; ++k) {
                    w[k] = qN[3 * k] * gc[0] + qN[3 * k + 1] * gc[1] + qN[3 * k + 2] * gc[2];
                    for (int ch = 0; ch < 3; ++ch) vN[3 * k + ch] += b[k] * gc[ch];
                }
                sh_basis_vjp(degree, d[0], d[1], d[2], w, g);
                const float dot = norm > 1e-12f ? d[0] * g[0] + d[1] * g[1] + d[2] * g[2] : 0.0f;
                for (int k = 0; k < 3; ++k) v_means[3 * n + k] += (g[k] - d[k] * dot) / norm;
            }
        }
    });
}

}  // extern "C"

// SSIM (Wang et al. 2004, the 3DGS loss's window): the five moments of x and y blurred by a
// separable Gaussian with zero padding, a column pass into a buffer, then a row pass per image
// row. Images are (B, H, W, C) channels last, so a row is W * C floats and the row pass steps
// by C. Every row is computed by one thread and the mean is summed over rows in order, so the
// bytes do not depend on the number of threads.
namespace {

struct Plane {  // one image's rows: H of W * C floats
    int H, W, C;
    int64_t row() const { return static_cast<int64_t>(W) * C; }
    int64_t image() const { return row() * H; }
};

inline vf loadu(const float* p) {
    vf v;
    std::memcpy(&v, p, sizeof v);
    return v;
}

inline void storeu(float* p, vf v) { std::memcpy(p, &v, sizeof v); }

// out[j] (a row of n = W * C floats) = sum over taps of taps[i] * in[j + (i - K / 2) * C],
// terms outside the row left out (taken as zeros from a padded copy: adding taps[i] * 0 leaves
// a sum as it is), 16 outputs at a time.
inline void row_blur(const float* in, int64_t n, int C, const float* taps, int K, float* out) {
    const int64_t reach = static_cast<int64_t>(K / 2) * C;
    thread_local std::vector<float> padded;
    padded.assign(static_cast<size_t>(n + 2 * reach + L), 0.0f);
    std::memcpy(padded.data() + reach, in, sizeof(float) * n);
    const float* src = padded.data();  // src[j + i * C] is in[j + (i - K / 2) * C] or a zero
    int64_t j = 0;
    for (; j + L <= n; j += L) {
        vf sum{};
        for (int i = 0; i < K; ++i) sum += splat(taps[i]) * loadu(src + j + i * C);
        storeu(out + j, sum);
    }
    for (; j < n; ++j) {
        float sum = 0.0f;
        for (int i = 0; i < K; ++i) sum += taps[i] * src[j + i * C];
        out[j] = sum;
    }
}

// Row pass of image row q of M column-blurred maps (map k's rows at cols[k]): m[k] points at
// its result, row k of buf (M rows of n floats).
template <int M>
inline void row_blurs(float* const* cols, int64_t q, int64_t n, int C, const float* taps, int K,
                      float* buf, float** m) {
    for (int k = 0; k < M; ++k) {
        m[k] = buf + k * n;
        row_blur(cols[k] + q * n, n, C, taps, K, m[k]);
    }
}

// The source rows of a column pass: output row r of an image of H rows gets taps[i] times row
// r + i - K / 2 where that row exists. Windows up to MAX_WINDOW rows (metrics.NATIVE_MAX_WINDOW).
constexpr int MAX_WINDOW = 31;

struct Column {
    int count = 0;
    int64_t rows[MAX_WINDOW];
    float weights[MAX_WINDOW];
};

inline Column column(int64_t q, int H, const float* taps, int K) {
    Column c;
    const int64_t first = q - q % H;
    const int r = static_cast<int>(q % H);
    for (int i = 0; i < K && c.count < MAX_WINDOW; ++i) {
        const int rr = r + i - K / 2;
        if (rr < 0 || rr >= H) continue;
        c.rows[c.count] = first + rr, c.weights[c.count] = taps[i], ++c.count;
    }
    return c;
}

// Column pass of the five moments: o_k (rows of n floats) = sum over the column's rows of
// weight * (x, y, x^2, y^2, xy), 16 floats at a time in registers.
inline void column_moments(const Column& c, const float* x, const float* y, int64_t n,
                           float* const* o) {
    auto lanes = [&](auto zero, auto load, auto store, int64_t j) {
        auto s0 = zero, s1 = zero, s2 = zero, s3 = zero, s4 = zero;
        for (int i = 0; i < c.count; ++i) {
            const auto a = load(x + c.rows[i] * n + j), b = load(y + c.rows[i] * n + j);
            const float t = c.weights[i];
            s0 += t * a, s1 += t * b, s2 += t * (a * a), s3 += t * (b * b), s4 += t * (a * b);
        }
        store(o[0] + j, s0), store(o[1] + j, s1), store(o[2] + j, s2), store(o[3] + j, s3);
        store(o[4] + j, s4);
    };
    int64_t j = 0;
    for (; j + L <= n; j += L) lanes(vf{}, loadu, storeu, j);
    for (; j < n; ++j)
        lanes(0.0f, [](const float* p) { return *p; }, [](float* p, float v) { *p = v; }, j);
}

// Column pass of M maps (map k at in + k * stride): o_k = sum over the column's rows of
// weight * map_k.
template <int M>
inline void column_maps(const Column& c, const float* in, int64_t stride, int64_t n,
                        float* const* o) {
    auto lanes = [&](auto zero, auto load, auto store, int64_t j) {
        for (int k = 0; k < M; ++k) {
            auto sum = zero;
            for (int i = 0; i < c.count; ++i) sum += c.weights[i] * load(in + k * stride + c.rows[i] * n + j);
            store(o[k] + j, sum);
        }
    };
    int64_t j = 0;
    for (; j + L <= n; j += L) lanes(vf{}, loadu, storeu, j);
    for (; j < n; ++j)
        lanes(0.0f, [](const float* p) { return *p; }, [](float* p, float v) { *p = v; }, j);
}

}  // namespace

extern "C" {

// Mean SSIM per image into mean (B,); where d is not null, d (3, B, H, W, C) gets the mean's
// derivatives with respect to the blurred mu_x, E[x^2] and E[xy] at each pixel (the backward's
// input). work holds 5 * B * H * W * C floats.
void pd_ssim_forward(const float* x, const float* y, int64_t B, int H, int W, int C,
                     const float* taps, int K, float c1, float c2, float* work, double* mean,
                     float* d, int threads) {
    const Plane p{H, W, C};
    const int64_t n = p.row(), rows = B * H, size = B * p.image();
    float* cols[5] = {work, work + size, work + 2 * size, work + 3 * size, work + 4 * size};
    parallel_tiles(rows, threads, [&](int64_t q) {
        float* o[5] = {cols[0] + q * n, cols[1] + q * n, cols[2] + q * n, cols[3] + q * n,
                       cols[4] + q * n};
        column_moments(column(q, H, taps, K), x, y, n, o);
    });
    std::vector<double> row_sums(rows);
    const float inv = 1.0f / static_cast<float>(p.image());
    parallel_tiles(rows, threads, [&](int64_t q) {
        std::vector<float> buf(6 * n);
        float* m[5];
        row_blurs<5>(cols, q, n, C, taps, K, buf.data(), m);
        const float* __restrict__ mx = m[0];
        const float* __restrict__ my = m[1];
        const float* __restrict__ xx = m[2];
        const float* __restrict__ yy = m[3];
        const float* __restrict__ xy = m[4];
        float* __restrict__ smap = buf.data() + 5 * n;
        float* __restrict__ d_mu = d != nullptr ? d + q * n : nullptr;
        float* __restrict__ d_xx = d != nullptr ? d + size + q * n : nullptr;
        float* __restrict__ d_xy = d != nullptr ? d + 2 * size + q * n : nullptr;
        // the map and its derivatives, L pixels at a time (the same arithmetic per lane)
        auto lanes = [&](auto load, auto store, int64_t j) {
            const auto ux = load(mx + j), uy = load(my + j);
            const auto A = 2.0f * ux * uy + c1, Bv = 2.0f * (load(xy + j) - ux * uy) + c2;
            const auto Cv = ux * ux + uy * uy + c1;
            const auto D = (load(xx + j) - ux * ux) + (load(yy + j) - uy * uy) + c2;
            const auto sm = A * Bv / (Cv * D);
            store(smap + j, sm);
            if (d_mu == nullptr) return;
            const auto CD = Cv * D;
            store(d_mu + j, (2.0f * uy * (Bv - A) / CD - 2.0f * ux * sm * (1.0f / Cv - 1.0f / D)) * inv);
            store(d_xx + j, -sm / D * inv);
            store(d_xy + j, 2.0f * A / CD * inv);
        };
        int64_t j = 0;
        for (; j + L <= n; j += L) lanes(loadu, storeu, j);
        for (; j < n; ++j)
            lanes([](const float* p) { return *p; }, [](float* p, float v) { *p = v; }, j);
        double sum = 0.0;
        for (int64_t j = 0; j < n; ++j) sum += smap[j];
        row_sums[q] = sum;
    });
    for (int64_t b = 0; b < B; ++b) {
        double total = 0.0;
        for (int r = 0; r < H; ++r) total += row_sums[b * H + r];
        mean[b] = total / static_cast<double>(p.image());
    }
}

// The gradient of sum_b grad[b] * mean SSIM_b with respect to x, into g (B, H, W, C): the three
// derivative maps of the forward blurred back (the window is symmetric, so its own adjoint)
// and combined per pixel. work holds 3 * B * H * W * C floats.
void pd_ssim_backward(const float* x, const float* y, const float* d, int64_t B, int H, int W,
                      int C, const float* taps, int K, const float* grad, float* work, float* g,
                      int threads) {
    const Plane p{H, W, C};
    const int64_t n = p.row(), rows = B * H, size = B * p.image();
    float* cols[3] = {work, work + size, work + 2 * size};
    parallel_tiles(rows, threads, [&](int64_t q) {
        float* o[3] = {cols[0] + q * n, cols[1] + q * n, cols[2] + q * n};
        column_maps<3>(column(q, H, taps, K), d, size, n, o);
    });
    parallel_tiles(rows, threads, [&](int64_t q) {
        std::vector<float> buf(3 * n);
        float* m[3];
        row_blurs<3>(cols, q, n, C, taps, K, buf.data(), m);
        const float scale = grad[q / H];
        const float* xr = x + q * n;
        const float* yr = y + q * n;
        float* gr = g + q * n;
        auto lanes = [&](auto load, auto store, int64_t j) {
            store(gr + j, (load(m[0] + j) + 2.0f * load(xr + j) * load(m[1] + j) +
                           load(yr + j) * load(m[2] + j)) * scale);
        };
        int64_t j = 0;
        for (; j + L <= n; j += L) lanes(loadu, storeu, j);
        for (; j < n; ++j)
            lanes([](const float* p) { return *p; }, [](float* p, float v) { *p = v; }, j);
    });
}

}  // extern "C"

// ---- The fit's loss (gs/fit.py, _Fit._loss) past the render: its gradient with respect to the
// render in closed form.
namespace {

// torch.sgn of a float: 1, -1, or +0 (for zeros and NaN).
inline float sgn(float x) { return static_cast<float>((x > 0.0f) - (x < 0.0f)); }

// clamp_min(x, m) (NaN stays NaN).
inline float clamp_min(float x, float m) { return x < m ? m : x; }

}  // namespace

extern "C" {

// The loss terms' sums, in double: sum |render_rgb - gt| over the P * 3 values; over the sky
// pixels, relu(1 - ed / sky_scale); over the K LiDAR pixels, |1 / clamp_min(ed, 1e-3) -
// target_inv|. terms gets the three sums.
void pd_fit_loss_terms(const float* render, const float* alphas, const float* gt, int64_t P,
                       int D, const uint8_t* sky, float sky_scale, const int64_t* pixels,
                       const float* target_inv, int64_t K, double* terms) {
    double l1 = 0.0, sky_sum = 0.0, depth_sum = 0.0;
    for (int64_t p = 0; p < P; ++p)
        for (int k = 0; k < 3; ++k) l1 += std::fabs(render[p * D + k] - gt[p * 3 + k]);
    for (int64_t p = 0; D == 4 && sky != nullptr && p < P; ++p) {
        if (!sky[p]) continue;
        const float r = 1.0f - render[p * 4 + 3] / clamp_min(alphas[p], 1e-10f) / sky_scale;
        sky_sum += r > 0.0f ? r : 0.0f;
    }
    for (int64_t k = 0; D == 4 && k < K; ++k) {
        const int64_t p = pixels[k];
        const float ed = render[p * 4 + 3] / clamp_min(alphas[p], 1e-10f);
        depth_sum += std::fabs(1.0f / clamp_min(ed, 1e-3f) - target_inv[k]);
    }
    terms[0] = l1, terms[1] = sky_sum, terms[2] = depth_sum;
}

// render (P, D): RGB and, when D == 4, the accumulated depth; alphas (P,); gt (P, 3);
// g_ssim (P, 3): the SSIM term's gradient; c_l1: the L1 term's per-element gradient. The
// expected depth is depth / clamp_min(alpha, 1e-10). Sky pixels (sky, or null) pull it to the
// sky: the gradient g_sky / sky_scale where 1 - ed / sky_scale > 0, negated. LiDAR pixels
// (pixels, K of them; target_inv = 1 / depth) pull its inverse (clamped at 1e-3) to the
// target: g_depth * sgn(1 / ed - target_inv) through the reciprocal. Writes d_render (P, D)
// and, when D == 4, d_alpha (P,).
void pd_fit_loss_backward(const float* render, const float* alphas, const float* gt,
                          const float* g_ssim, int64_t P, int D, float c_l1,
                          const uint8_t* sky, float g_sky, float sky_scale,
                          const int64_t* pixels, const float* target_inv, int64_t K,
                          float g_depth, float* d_render, float* d_alpha) {
    for (int64_t p = 0; p < P; ++p)
        for (int k = 0; k < 3; ++k) {
            const int64_t i = p * 3 + k;
            d_render[p * D + k] = c_l1 * sgn(render[p * D + k] - gt[i]) + g_ssim[i];
        }
    if (D != 4) return;
    std::vector<float> d_ed(P, 0.0f);
    for (int64_t p = 0; sky != nullptr && p < P; ++p) {
        if (!sky[p]) continue;
        const float ed = render[p * 4 + 3] / clamp_min(alphas[p], 1e-10f);
        const float r = 1.0f - ed / sky_scale;
        const float g = (r > 0.0f || r != r) ? g_sky : 0.0f;  // relu's backward: 0 where r <= 0
        d_ed[p] += -g / sky_scale;
    }
    for (int64_t k = 0; k < K; ++k) {
        const int64_t p = pixels[k];
        const float ed = render[p * 4 + 3] / clamp_min(alphas[p], 1e-10f);
        const float inv = 1.0f / clamp_min(ed, 1e-3f);
        const float g = -(g_depth * sgn(inv - target_inv[k])) * (inv * inv);
        d_ed[p] += ed >= 1e-3f ? g : 0.0f;
    }
    for (int64_t p = 0; p < P; ++p) {
        const float e = d_ed[p], a = alphas[p], ac = clamp_min(a, 1e-10f);
        d_render[p * 4 + 3] = e / ac;
        d_alpha[p] = a >= 1e-10f ? -e * ((render[p * 4 + 3] / ac) / ac) : 0.0f;
    }
}

}  // extern "C"

// The scene graph's placement (graph.place): a node's Gaussians move by its box's pose.
namespace {

// Rows of a copy each task takes.
constexpr int64_t PLACE_CHUNK = 16384;

// dst = src, n floats, on `threads` threads.
void copy_floats(float* dst, const float* src, int64_t n, int threads) {
    parallel_tiles((n + PLACE_CHUNK - 1) / PLACE_CHUNK, threads, [&](int64_t t) {
        const int64_t lo = t * PLACE_CHUNK, hi = lo + PLACE_CHUNK < n ? lo + PLACE_CHUNK : n;
        std::memcpy(dst + lo, src + lo, static_cast<size_t>(hi - lo) * sizeof(float));
    });
}

// box (4, 4) row-major: out = R m + t.
void place_mean(const float* box, const float* m, float* out) {
    for (int i = 0; i < 3; ++i) {
        const float* r = box + 4 * i;
        float acc = 0.0f;
        for (int j = 0; j < 3; ++j) acc += r[j] * m[j];
        out[i] = acc + r[3];
    }
}

// out = a (x) b, quaternions w x y z.
void quat_product(const float* a, const float* b, float* out) {
    const float aw = a[0], ax = a[1], ay = a[2], az = a[3];
    const float bw = b[0], bx = b[1], by = b[2], bz = b[3];
    out[0] = aw * bw - ax * bx - ay * by - az * bz;
    out[1] = aw * bx + ax * bw + ay * bz - az * by;
    out[2] = aw * by - ax * bz + ay * bw + az * bx;
    out[3] = aw * bz + ax * by - ay * bx + az * bw;
}

// g_m = R^T g.
void place_mean_vjp(const float* box, const float* g, float* out) {
    for (int j = 0; j < 3; ++j) out[j] = box[j] * g[0] + box[4 + j] * g[1] + box[8 + j] * g[2];
}

// The gradient of b in a (x) b: the transposed product matrix of a times g.
void quat_product_vjp(const float* a, const float* g, float* out) {
    const float aw = a[0], ax = a[1], ay = a[2], az = a[3];
    const float g0 = g[0], g1 = g[1], g2 = g[2], g3 = g[3];
    out[0] = aw * g0 + ax * g1 + ay * g2 + az * g3;
    out[1] = -ax * g0 + aw * g1 + az * g2 - ay * g3;
    out[2] = -ay * g0 - az * g1 + aw * g2 + ax * g3;
    out[3] = -az * g0 + ay * g1 - ax * g2 + aw * g3;
}

}  // namespace

extern "C" {

// The Gaussians of one scene frame: out_means (N, 3), out_quats (N, 4) and out_opac (N,) are
// copies of means, quats and opacities, but for the M rows `rows` of nodes `node` (node k's box
// (K, 4, 4) row-major and its rotation nq (K, 4)): means moved by the box, quats turned by its
// rotation, and the opacity -inf where present[k] is 0 (the node is not in this frame).
void pd_place_forward(const float* means, const float* quats, const float* opac, int64_t N,
                      const int64_t* rows, const int64_t* node, int64_t M, const float* box,
                      const float* nq, const uint8_t* present, float* out_means,
                      float* out_quats, float* out_opac, int threads) {
    copy_floats(out_means, means, N * 3, threads);
    copy_floats(out_quats, quats, N * 4, threads);
    copy_floats(out_opac, opac, N, threads);
    parallel_tiles((M + PLACE_CHUNK - 1) / PLACE_CHUNK, threads, [&](int64_t t) {
        const int64_t hi = (t + 1) * PLACE_CHUNK < M ? (t + 1) * PLACE_CHUNK : M;
        for (int64_t i = t * PLACE_CHUNK; i < hi; ++i) {
            const int64_t r = rows[i], k = node[i];
            place_mean(box + 16 * k, means + 3 * r, out_means + 3 * r);
            quat_product(nq + 4 * k, quats + 4 * r, out_quats + 4 * r);
            if (!present[k]) out_opac[r] = -INFINITY;
        }
    });
}

// The gradients of pd_place_forward's inputs from those of its outputs (each pointer pair may
// be null: that gradient is not wanted). The rows of nodes get the moved rows' gradients; a
// row of a node not in the frame gets no opacity gradient.
void pd_place_backward(const float* g_means, const float* g_quats, const float* g_opac,
                       int64_t N, const int64_t* rows, const int64_t* node, int64_t M,
                       const float* box, const float* nq, const uint8_t* present,
                       float* v_means, float* v_quats, float* v_opac, int threads) {
    // A row outside the nodes keeps its gradient.
    if (g_means != nullptr) copy_floats(v_means, g_means, N * 3, threads);
    if (g_quats != nullptr) copy_floats(v_quats, g_quats, N * 4, threads);
    if (g_opac != nullptr) copy_floats(v_opac, g_opac, N, threads);
    parallel_tiles((M + PLACE_CHUNK - 1) / PLACE_CHUNK, threads, [&](int64_t t) {
        const int64_t hi = (t + 1) * PLACE_CHUNK < M ? (t + 1) * PLACE_CHUNK : M;
        for (int64_t i = t * PLACE_CHUNK; i < hi; ++i) {
            const int64_t r = rows[i], k = node[i];
            if (g_means != nullptr) place_mean_vjp(box + 16 * k, g_means + 3 * r, v_means + 3 * r);
            if (g_quats != nullptr) quat_product_vjp(nq + 4 * k, g_quats + 4 * r, v_quats + 4 * r);
            if (g_opac != nullptr && !present[k]) v_opac[r] = 0.0f;
        }
    });
}

}  // extern "C"
