// Python bindings of the kernels in _composite.cpp, built at install (setup.py) into one
// extension module per instruction set: PD_MODULE names it, the compiler flags pick the vector
// unit. Each entry point takes numpy arrays and checks their dtype, layout and size against the
// sizes it is given before a kernel reads or writes them, so a wrong call raises TypeError or
// ValueError instead of reading past an array.

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <algorithm>
#include <optional>
#include <stdexcept>
#include <string>

#include "_composite.cpp"

namespace py = pybind11;

namespace {

std::string what(const char* name, const py::array& a) {
    std::string shape;
    for (py::ssize_t k = 0; k < a.ndim(); ++k) shape += (k ? ", " : "") + std::to_string(a.shape(k));
    return std::string(name) + " (shape (" + shape + "), " + std::string(py::str(a.dtype())) + ")";
}

// The data of `a`, which must be a C-contiguous array of T with at least `need` elements (and
// writeable when `write`).
template <class T>
T* data(const py::array& a, const char* name, int64_t need, bool write = false) {
    if (!py::array_t<T>::check_(a))
        throw py::type_error(what(name, a) + ": expected " + std::string(py::str(py::dtype::of<T>())));
    if (!(a.flags() & py::array::c_style))
        throw py::type_error(what(name, a) + ": expected a C-contiguous array");
    if (a.size() < need)
        throw py::value_error(what(name, a) + ": expected at least " + std::to_string(need) + " values");
    if (write && !a.writeable()) throw py::value_error(what(name, a) + ": not writeable");
    return static_cast<T*>(const_cast<void*>(a.data()));
}

template <class T>
T* data(const std::optional<py::array>& a, const char* name, int64_t need, bool write = false) {
    return a ? data<T>(*a, name, need, write) : nullptr;
}

// `rows` evenly spaced rows of `width` float32 values: a C-contiguous array, or a slice of
// columns of a wider table (table[:, 6:9]), read and written in place. (pointer, floats from
// one row to the next)
std::pair<float*, int> rows(const py::array& a, const char* name, int width, int64_t n) {
    bool ok = py::array_t<float>::check_(a) && a.ndim() >= 1 && a.shape(a.ndim() - 1) == width &&
              a.size() == n * width && a.strides(a.ndim() - 1) == 4;
    const py::ssize_t step = ok && a.ndim() > 1 && a.shape(a.ndim() - 2) > 1 ? a.strides(a.ndim() - 2)
                                                                             : 4 * width;
    ok = ok && step >= 4 * width && step % 4 == 0;
    py::ssize_t inner = step;  // bytes from one row to the next, across the leading axes too
    for (py::ssize_t k = a.ndim() - 2; ok && k >= 0; --k) {
        if (a.shape(k) > 1 && a.strides(k) != inner) ok = false;
        inner *= a.shape(k);
    }
    if (!ok)
        throw py::type_error(what(name, a) + ": expected " + std::to_string(n) +
                             " evenly spaced rows of " + std::to_string(width) + " float32 values");
    return {static_cast<float*>(const_cast<void*>(a.data())), static_cast<int>(step / 4)};
}

int64_t dim(const py::array& a, int k) { return a.ndim() > k ? a.shape(k) : 0; }

void composite_forward(const py::array& table, const py::array& ids, const py::array& offsets,
                       const py::array& counts, int ts, int tiles_x, int tiles_y,
                       const py::array& bg, const py::array& render, const py::array& trans,
                       const py::array& last, const py::array& reach, int threads) {
    const int64_t n_rows = dim(table, 0), F = dim(table, 1), n_tiles = dim(offsets, 0);
    const int C = dim(render, 0), H = dim(render, 1), W = dim(render, 2), D = dim(render, 3);
    if (D < 1 || D > MAX_CHANNELS || F != 6 + D || render.ndim() != 4 ||
        n_tiles != static_cast<int64_t>(C) * tiles_x * tiles_y)
        throw py::value_error(what("composite_forward: table", table) + ", " + what("render", render) +
                              ": 1 to 4 channels, 6 + D columns, C * tiles offsets");
    const int64_t pixels = static_cast<int64_t>(C) * H * W;
    pd_composite_forward(data<float>(table, "table", n_rows * F), n_rows, F,
                         data<int64_t>(ids, "ids", 0), data<int64_t>(offsets, "offsets", n_tiles),
                         data<int64_t>(counts, "counts", n_tiles), n_tiles, ts, tiles_x, tiles_y,
                         C, H, W, D, data<float>(bg, "bg", C * D),
                         data<float>(render, "render", pixels * D, true),
                         data<float>(trans, "trans", pixels, true),
                         data<int64_t>(last, "last", pixels, true),
                         data<float>(reach, "reach", 2 * n_rows, true), threads);
}

py::array_t<float> composite_backward(const py::array& table, const py::array& ids,
                                      const py::array& offsets, const py::array& counts, int ts,
                                      int tiles_x, int tiles_y, const py::array& bg,
                                      const py::array& trans, const py::array& last,
                                      const py::array& d_render, const py::array& d_alpha,
                                      const py::array& reach, int threads) {
    const int64_t n_rows = dim(table, 0), F = dim(table, 1), n_tiles = dim(offsets, 0);
    const int C = dim(d_render, 0), H = dim(d_render, 1), W = dim(d_render, 2), D = dim(d_render, 3);
    if (D < 1 || D > MAX_CHANNELS || F != 6 + D || d_render.ndim() != 4 ||
        n_tiles != static_cast<int64_t>(C) * tiles_x * tiles_y)
        throw py::value_error(what("composite_backward: table", table) + ", " +
                              what("d_render", d_render) + ": 1 to 4 channels, 6 + D columns");
    const int64_t pixels = static_cast<int64_t>(C) * H * W, n_isects = ids.size();
    py::array_t<float> grads({n_isects, F});
    pd_composite_backward(data<float>(table, "table", n_rows * F), n_rows, F,
                          data<int64_t>(ids, "ids", n_isects), data<int64_t>(offsets, "offsets", n_tiles),
                          data<int64_t>(counts, "counts", n_tiles), n_tiles, ts, tiles_x, tiles_y,
                          C, H, W, D, data<float>(bg, "bg", C * D), data<float>(trans, "trans", pixels),
                          data<int64_t>(last, "last", pixels), data<float>(d_render, "d_render", pixels * D),
                          data<float>(d_alpha, "d_alpha", pixels), data<float>(reach, "reach", 2 * n_rows),
                          grads.mutable_data(), threads);
    return grads;
}

// (ids, offsets, counts) of the tile lists: depths (C*N,), means2d and radii (C*N, 2).
py::tuple bin_lists(const py::array& depths, const py::array& means2d, const py::array& radii,
                    int64_t n_per_cam, int ts, int tiles_x, int tiles_y, int64_t n_tiles) {
    const int64_t n = depths.size();
    const float* m = data<float>(means2d, "means2d", 2 * n);
    const float* r = data<float>(radii, "radii", 2 * n);
    py::array_t<int64_t> order(n), counts(n_tiles), offsets(n_tiles);
    int64_t* c = counts.mutable_data();
    std::fill(c, c + n_tiles, 0);
    const int64_t visible = pd_bin_count(data<float>(depths, "depths", n), m, r, n, n_per_cam, ts,
                                         tiles_x, tiles_y, order.mutable_data(), c);
    int64_t* o = offsets.mutable_data();
    int64_t total = 0;
    for (int64_t t = 0; t < n_tiles; ++t) o[t] = total, total += c[t];
    py::array_t<int64_t> ids(total);
    std::vector<int64_t> fill(o, o + n_tiles);
    pd_bin_fill(order.data(), visible, m, r, n_per_cam, ts, tiles_x, tiles_y, fill.data(),
                ids.mutable_data());
    return py::make_tuple(ids, offsets, counts);
}

py::array_t<float> sum_by_gaussian(const py::array& grads, const py::array& ids, int64_t n,
                                   int threads) {
    const int64_t n_isects = ids.size(), F = dim(grads, 1);
    py::array_t<float> out({n, F});
    const int64_t* id = data<int64_t>(ids, "ids", n_isects);
    for (int64_t e = 0; e < n_isects; ++e)
        if (id[e] < 0 || id[e] >= n) throw py::value_error("sum_by_gaussian: an id outside the Gaussians");
    pd_sum_by_gaussian(data<float>(grads, "grads", n_isects * F), id, n_isects, F, n,
                       out.mutable_data(), threads);
    return out;
}

void grad_norms(const py::array& grads, float sx, float sy, const py::array& radii,
                const py::array& grad2d, const py::array& count, int threads) {
    const int C = dim(radii, 0);
    const int64_t N = dim(radii, 1);
    auto [g, stride] = rows(grads, "grads", 2, C * N);
    pd_grad_norms(g, stride, C, N, sx, sy, data<int32_t>(radii, "radii", C * N),
                  data<float>(grad2d, "grad2d", N, true), data<float>(count, "count", N, true), threads);
}

void project_forward(const py::array& means, const py::array& quats, const py::array& scales,
                     const py::array& opacities, const py::array& viewmats, const py::array& Ks,
                     int width, int height, float near, float far, float eps2d, float radius_clip,
                     const py::array& means2d, const py::array& conics, const py::array& depths,
                     const py::array& radii, const std::optional<py::array>& table, int depth_column,
                     int threads) {
    const int64_t N = dim(means, 0);
    const int C = dim(viewmats, 0);
    const int F = table ? dim(*table, 1) : 0;
    if (table && (dim(*table, 0) != C * N || F < 6 || depth_column >= F))
        throw py::value_error(what("project_forward: table", *table) + " for " + std::to_string(C) +
                              " x " + std::to_string(N) + " projections");
    pd_project_forward(data<float>(means, "means", 3 * N), data<float>(quats, "quats", 4 * N),
                       data<float>(scales, "scales", 3 * N), data<float>(opacities, "opacities", N),
                       data<float>(viewmats, "viewmats", 16 * C), data<float>(Ks, "Ks", 9 * C), N, C,
                       width, height, near, far, eps2d, radius_clip,
                       data<float>(means2d, "means2d", 2 * C * N, true),
                       data<float>(conics, "conics", 3 * C * N, true),
                       data<float>(depths, "depths", C * N, true),
                       data<int32_t>(radii, "radii", 2 * C * N, true),
                       data<float>(table, "table", C * N * F, true), F, depth_column, threads);
}

py::tuple project_backward(const py::array& means, const py::array& quats, const py::array& scales,
                           const py::array& viewmats, const py::array& Ks, int width, int height,
                           float near, float far, float eps2d, const py::array& v_means2d,
                           const py::array& v_conics, const py::array& v_depths, int threads) {
    const int64_t N = dim(means, 0);
    const int C = dim(viewmats, 0);
    auto [v2, s2] = rows(v_means2d, "v_means2d", 2, C * N);
    auto [vc, sc] = rows(v_conics, "v_conics", 3, C * N);
    auto [vd, sd] = rows(v_depths, "v_depths", 1, C * N);
    py::array_t<float> vm({N, int64_t{3}}), vq({N, int64_t{4}}), vs({N, int64_t{3}});
    std::fill(vm.mutable_data(), vm.mutable_data() + 3 * N, 0.0f);
    std::fill(vq.mutable_data(), vq.mutable_data() + 4 * N, 0.0f);
    std::fill(vs.mutable_data(), vs.mutable_data() + 3 * N, 0.0f);
    pd_project_backward(data<float>(means, "means", 3 * N), data<float>(quats, "quats", 4 * N),
                        data<float>(scales, "scales", 3 * N), data<float>(viewmats, "viewmats", 16 * C),
                        data<float>(Ks, "Ks", 9 * C), N, C, width, height, near, far, eps2d, v2, s2,
                        vc, sc, vd, sd, vm.mutable_data(), vq.mutable_data(), vs.mutable_data(), threads);
    return py::make_tuple(vm, vq, vs);
}

void check_sh(int degree, int64_t KN) {
    if (degree < 0 || degree > 3 || KN + 1 < (degree + 1) * (degree + 1))
        throw py::value_error("sh: degree " + std::to_string(degree) + " with " +
                              std::to_string(KN + 1) + " coefficients");
}

void sh_forward(int degree, const py::array& means, const py::array& c0, const py::array& cN,
                const py::array& campos, const py::array& visible, const py::array& colors,
                int threads) {
    const int64_t N = dim(means, 0), KN = dim(cN, 1);
    const int C = dim(campos, 0);
    check_sh(degree, KN);
    auto [out, stride] = rows(colors, "colors", 3, C * N);
    pd_sh_forward(degree, data<float>(means, "means", 3 * N), data<float>(c0, "c0", 3 * N),
                  data<float>(cN, "cN", N * KN * 3), KN, data<float>(campos, "campos", 3 * C), N, C,
                  reinterpret_cast<const uint8_t*>(data<bool>(visible, "visible", C * N)), out, stride,
                  threads);
}

void sh_backward(int degree, const py::array& means, const py::array& c0, const py::array& cN,
                 const py::array& campos, const py::array& colors, const py::array& v_colors,
                 const py::array& v_means, const py::array& v_c0, const py::array& v_cN, int threads) {
    const int64_t N = dim(means, 0), KN = dim(cN, 1);
    const int C = dim(campos, 0);
    check_sh(degree, KN);
    auto [col, s_col] = rows(colors, "colors", 3, C * N);
    auto [vcol, s_v] = rows(v_colors, "v_colors", 3, C * N);
    pd_sh_backward(degree, data<float>(means, "means", 3 * N), data<float>(c0, "c0", 3 * N),
                   data<float>(cN, "cN", N * KN * 3), KN, data<float>(campos, "campos", 3 * C), N, C,
                   col, s_col, vcol, s_v, data<float>(v_means, "v_means", 3 * N, true),
                   data<float>(v_c0, "v_c0", 3 * N, true), data<float>(v_cN, "v_cN", N * KN * 3, true),
                   threads);
}

int check_window(const py::array& taps) {
    const int K = taps.size();
    if (K < 1 || K > MAX_WINDOW) throw py::value_error("ssim: a window of 1 to 31 taps");
    return K;
}

py::tuple ssim_forward(const py::array& x, const py::array& y, const py::array& taps, float c1,
                       float c2, bool derivatives, int threads) {
    const int64_t B = dim(x, 0);
    const int H = dim(x, 1), W = dim(x, 2), C = dim(x, 3), K = check_window(taps);
    const int64_t size = B * H * W * C;
    if (x.ndim() != 4) throw py::value_error(what("ssim: x", x) + ": expected (B, H, W, C)");
    py::array_t<double> mean(B);
    std::vector<float> work(5 * size);
    py::object d = py::none();
    float* d_data = nullptr;
    if (derivatives) {
        py::array_t<float> maps({int64_t{3}, B, int64_t{H}, int64_t{W}, int64_t{C}});
        d_data = maps.mutable_data();
        d = maps;
    }
    pd_ssim_forward(data<float>(x, "x", size), data<float>(y, "y", size), B, H, W, C,
                    data<float>(taps, "taps", K), K, c1, c2, work.data(), mean.mutable_data(), d_data,
                    threads);
    return py::make_tuple(mean, d);
}

py::array_t<float> ssim_backward(const py::array& x, const py::array& y, const py::array& d,
                                 const py::array& taps, const py::array& grad, int threads) {
    const int64_t B = dim(x, 0);
    const int H = dim(x, 1), W = dim(x, 2), C = dim(x, 3), K = check_window(taps);
    const int64_t size = B * H * W * C;
    if (x.ndim() != 4) throw py::value_error(what("ssim: x", x) + ": expected (B, H, W, C)");
    py::array_t<float> g({B, int64_t{H}, int64_t{W}, int64_t{C}});
    std::vector<float> work(3 * size);
    pd_ssim_backward(data<float>(x, "x", size), data<float>(y, "y", size), data<float>(d, "d", 3 * size),
                     B, H, W, C, data<float>(taps, "taps", K), K, data<float>(grad, "grad", B),
                     work.data(), g.mutable_data(), threads);
    return g;
}

// The LiDAR pixels' ids must lie in the image (they index render and alphas).
const int64_t* pixel_ids(const py::array& pixels, int64_t P) {
    const int64_t* p = data<int64_t>(pixels, "pixels", pixels.size());
    for (int64_t k = 0; k < pixels.size(); ++k)
        if (p[k] < 0 || p[k] >= P) throw py::value_error("fit loss: a LiDAR pixel outside the image");
    return p;
}

py::array_t<double> fit_loss_terms(const py::array& render, const py::array& alphas,
                                   const py::array& gt, const std::optional<py::array>& sky,
                                   float sky_scale, const py::array& pixels,
                                   const py::array& target_inv) {
    const int64_t P = dim(render, 0), K = pixels.size();
    const int D = dim(render, 1);
    if (D != 3 && D != 4) throw py::value_error(what("fit loss: render", render) + ": expected (P, 3 or 4)");
    py::array_t<double> terms(3);
    pd_fit_loss_terms(data<float>(render, "render", P * D), data<float>(alphas, "alphas", P),
                      data<float>(gt, "gt", 3 * P), P, D,
                      reinterpret_cast<const uint8_t*>(data<bool>(sky, "sky", P)), sky_scale,
                      pixel_ids(pixels, P), data<float>(target_inv, "target_inv", K), K,
                      terms.mutable_data());
    return terms;
}

py::tuple fit_loss_backward(const py::array& render, const py::array& alphas, const py::array& gt,
                            const py::array& g_ssim, float c_l1, const std::optional<py::array>& sky,
                            float g_sky, float sky_scale, const py::array& pixels,
                            const py::array& target_inv, float g_depth) {
    const int64_t P = dim(render, 0), K = pixels.size();
    const int D = dim(render, 1);
    if (D != 3 && D != 4) throw py::value_error(what("fit loss: render", render) + ": expected (P, 3 or 4)");
    py::array_t<float> d_render({P, int64_t{D}}), d_alpha(P);
    pd_fit_loss_backward(data<float>(render, "render", P * D), data<float>(alphas, "alphas", P),
                         data<float>(gt, "gt", 3 * P), data<float>(g_ssim, "g_ssim", 3 * P), P, D, c_l1,
                         reinterpret_cast<const uint8_t*>(data<bool>(sky, "sky", P)), g_sky, sky_scale,
                         pixel_ids(pixels, P), data<float>(target_inv, "target_inv", K), K, g_depth,
                         d_render.mutable_data(), d_alpha.mutable_data());
    return py::make_tuple(d_render, d_alpha);
}

// The placement's node rows: rows and their nodes (M,) int64 (rows < N, nodes < K), the nodes'
// boxes (K, 4, 4) and rotations (K, 4) float32, present (K,) bool.
struct NodeRows {
    const int64_t *rows, *node;
    int64_t M;
    const float *box, *nq;
    const uint8_t* present;
};

NodeRows node_rows(const py::array& rows, const py::array& node, const py::array& box,
                   const py::array& nq, const py::array& present, int64_t N) {
    const int64_t M = rows.size(), K = dim(box, 0);
    if (node.size() != M || box.size() != 16 * K || nq.size() != 4 * K || present.size() != K)
        throw py::value_error("place: rows " + what("", rows) + ", nodes " + what("", node) + ", boxes " +
                              what("", box) + ", rotations " + what("", nq) + ", present " +
                              what("", present));
    const int64_t* r = data<int64_t>(rows, "rows", M);
    const int64_t* k = data<int64_t>(node, "nodes", M);
    for (int64_t i = 0; i < M; ++i)
        if (r[i] < 0 || r[i] >= N || k[i] < 0 || k[i] >= K)
            throw py::value_error("place: a row or node outside the Gaussians or nodes");
    return {r, k, M, data<float>(box, "boxes", 16 * K), data<float>(nq, "rotations", 4 * K),
            reinterpret_cast<const uint8_t*>(data<bool>(present, "present", K))};
}

py::tuple place_forward(const py::array& means, const py::array& quats, const py::array& opacities,
                        const py::array& rows, const py::array& node, const py::array& box,
                        const py::array& nq, const py::array& present, int threads) {
    const int64_t N = dim(means, 0);
    const NodeRows n = node_rows(rows, node, box, nq, present, N);
    py::array_t<float> m({N, int64_t{3}}), q({N, int64_t{4}}), o(N);
    pd_place_forward(data<float>(means, "means", 3 * N), data<float>(quats, "quats", 4 * N),
                     data<float>(opacities, "opacities", N), N, n.rows, n.node, n.M, n.box, n.nq,
                     n.present, m.mutable_data(), q.mutable_data(), o.mutable_data(), threads);
    return py::make_tuple(m, q, o);
}

// The gradients of place_forward's inputs from those of its outputs (None: not wanted).
py::tuple place_backward(const std::optional<py::array>& g_means,
                         const std::optional<py::array>& g_quats,
                         const std::optional<py::array>& g_opacities, const py::array& rows,
                         const py::array& node, const py::array& box, const py::array& nq,
                         const py::array& present, int threads) {
    const auto& first = g_means ? g_means : g_quats ? g_quats : g_opacities;
    if (!first) return py::make_tuple(py::none(), py::none(), py::none());
    const int64_t N = dim(*first, 0);
    const NodeRows n = node_rows(rows, node, box, nq, present, N);
    auto like = [&](const std::optional<py::array>& g, int64_t width) -> std::optional<py::array_t<float>> {
        if (!g) return std::nullopt;
        return width == 1 ? py::array_t<float>(N) : py::array_t<float>({N, width});
    };
    auto vm = like(g_means, 3), vq = like(g_quats, 4), vo = like(g_opacities, 1);
    pd_place_backward(data<float>(g_means, "g_means", 3 * N), data<float>(g_quats, "g_quats", 4 * N),
                      data<float>(g_opacities, "g_opacities", N), N, n.rows, n.node, n.M, n.box, n.nq,
                      n.present, vm ? vm->mutable_data() : nullptr, vq ? vq->mutable_data() : nullptr,
                      vo ? vo->mutable_data() : nullptr, threads);
    auto out = [](const std::optional<py::array_t<float>>& a) -> py::object {
        return a ? py::object(*a) : py::object(py::none());
    };
    return py::make_tuple(out(vm), out(vq), out(vo));
}

}  // namespace

PYBIND11_MODULE(PD_MODULE, m) {
    m.doc() = "The fused CPU rasterizer's kernels, built for one instruction set.";
    m.attr("lanes") = L;
    m.attr("max_channels") = MAX_CHANNELS;
    m.attr("max_window") = MAX_WINDOW;
    m.def("composite_forward", &composite_forward);
    m.def("composite_backward", &composite_backward);
    m.def("bin_lists", &bin_lists);
    m.def("sum_by_gaussian", &sum_by_gaussian);
    m.def("grad_norms", &grad_norms);
    m.def("project_forward", &project_forward);
    m.def("project_backward", &project_backward);
    m.def("sh_forward", &sh_forward);
    m.def("sh_backward", &sh_backward);
    m.def("ssim_forward", &ssim_forward);
    m.def("ssim_backward", &ssim_backward);
    m.def("fit_loss_terms", &fit_loss_terms);
    m.def("fit_loss_backward", &fit_loss_backward);
    m.def("place_forward", &place_forward);
    m.def("place_backward", &place_backward);
}
