// Grid-bucketed ORB extraction of a frame's images in compiled code: the method of features.py
// (each pyramid level detected as a one-level OpenCV ORB detects it, FAST at the first threshold
// and again at the low one when that finds too few; the best keypoints of each (level, grid cell)
// first; descriptors for the kept ones), run on a few threads without Python's lock. The
// keypoints stay in C++ vectors until the result: making a cv2.KeyPoint object per candidate and
// reading its fields back in Python cost more than the detection's Harris scores.
//
// The detection is ORB's own sequence of public OpenCV steps (FAST, the border filter, the best
// 2n by FAST score, the Harris score, the best n), with the Harris score and the orientation
// computed here: the orientation only for the keypoints the grid keeps (ORB orients all n found,
// 2.5x as many on KITTI), so a pass at the first threshold that finds too few costs only its
// FAST. Scores and angles are OpenCV's, bit for bit (test_vo compares with its ORB).
//
// Built by CMakeLists.txt (scripts/setup) as coop_slam/vo/_orb_native.*.so; features.py drives it.

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <condition_variable>
#include <cstdint>
#include <exception>
#include <memory>
#include <mutex>
#include <numeric>
#include <stdexcept>
#include <system_error>
#include <thread>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/features2d.hpp>
#include <opencv2/imgproc.hpp>

namespace py = pybind11;

namespace {

struct Image {
  std::vector<cv::Mat> levels;  // level 0 wraps the caller's array
  std::vector<std::vector<cv::KeyPoint>> found;  // per level
  std::vector<std::vector<cv::KeyPoint>> chosen;  // per level, after bucketing
  std::vector<std::vector<cv::KeyPoint>> described;  // per level, as ORB's compute returns them
  std::vector<cv::Mat> descriptors;  // per level
  // Progress (under the extraction's lock): each stage waits for the one before it.
  bool pyramid_done = false;
  int levels_pending = 0;  // detection items not finished
  bool bucketed = false;
  bool failed = false;  // an item failed (its error reaches the caller): later ones skip
};

// Runs a function when it goes out of scope (also when an exception leaves it).
template <typename Fn>
struct OnExit {
  Fn fn;
  ~OnExit() { fn(); }
};
template <typename Fn>
OnExit<Fn> on_exit(Fn fn) {
  return OnExit<Fn>{fn};
}

// Work items handed out in order to whichever thread asks first; an item's errors are kept and
// rethrown by run() after every thread stopped.
class Workers {
 public:
  template <typename Fn>
  static void run(int n_items, int n_threads, Fn work) {
    std::atomic<int> next{0};
    std::exception_ptr error;
    std::mutex error_lock;
    auto drain = [&]() {
      for (int item = next++; item < n_items; item = next++) {
        try {
          work(item);
        } catch (...) {
          std::lock_guard<std::mutex> hold(error_lock);
          if (!error) error = std::current_exception();
        }
      }
    };
    std::vector<std::thread> helpers;
    try {
      for (int t = 1; t < std::min(n_threads, n_items); ++t) helpers.emplace_back(drain);
    } catch (const std::system_error &) {
      // No more threads (a resource limit): the ones started and this one do every item.
    }
    drain();
    for (auto &helper : helpers) helper.join();
    if (error) std::rethrow_exception(error);
  }
};

// The caller's grey image, checked: a clear error rather than a crash on a wrong array.
py::array_t<uint8_t> checked_gray(const py::handle &object, const std::string &name) {
  auto array = py::cast<py::array>(object);
  if (array.ndim() != 2 || !py::isinstance<py::array_t<uint8_t>>(array) ||
      !(array.flags() & py::array::c_style) || array.shape(0) < 1 || array.shape(1) < 1) {
    throw std::invalid_argument(name + ": expected a non-empty C-contiguous 2D uint8 array");
  }
  return py::cast<py::array_t<uint8_t>>(array);
}

// A cv::Mat over the array's pixels (the array must outlive it).
cv::Mat wrap(const py::array_t<uint8_t> &array) {
  return cv::Mat(static_cast<int>(array.shape(0)), static_cast<int>(array.shape(1)), CV_8UC1,
                 const_cast<uint8_t *>(array.data()));
}

// levels[0] given; each level resized from the one above it, sized in float32 as OpenCV's ORB
// sizes them (at .5 the rounding differs from double's, e.g. 540 / 1.2**3).
void build_levels(std::vector<cv::Mat> &levels, const std::vector<float> &scales32) {
  const cv::Mat &base = levels[0];
  for (size_t l = 1; l < scales32.size(); ++l) {
    const float f = 1.0f / scales32[l];
    const int w = std::max(1, static_cast<int>(std::nearbyint(static_cast<float>(base.cols) * f)));
    const int h = std::max(1, static_cast<int>(std::nearbyint(static_cast<float>(base.rows) * f)));
    cv::resize(levels[l - 1], levels[l], cv::Size(w, h), 0, 0, cv::INTER_LINEAR_EXACT);
  }
}

// Harris corner score of the 7 x 7 block around pixel (x, y): det - 0.04 trace^2 of the summed
// products of 3 x 3 Sobel gradients, normalised and evaluated in float32 in the order OpenCV's
// ORB does (its HARRIS_SCORE, bit for bit: the bucketing's order follows the scores).
float harris_score(const cv::Mat &image, int x, int y) {
  constexpr int kBlock = 7;
  constexpr float kHarrisK = 0.04f;
  const int step = static_cast<int>(image.step);
  int sxx = 0, syy = 0, sxy = 0;
  for (int dy = -kBlock / 2; dy <= kBlock / 2; ++dy) {
    const uint8_t *row = image.ptr<uint8_t>(y + dy) + x;
    for (int dx = -kBlock / 2; dx <= kBlock / 2; ++dx) {
      const uint8_t *p = row + dx;
      const uint8_t *up = p - step, *down = p + step;
      const int gx = 2 * (p[1] - p[-1]) + (up[1] - up[-1]) + (down[1] - down[-1]);
      const int gy = 2 * (down[0] - up[0]) + (down[-1] - up[-1]) + (down[1] - up[1]);
      sxx += gx * gx;
      syy += gy * gy;
      sxy += gx * gy;
    }
  }
  const float norm = 1.0f / (4 * kBlock * 255.0f);  // the gradients' largest value
  const float norm4 = norm * norm * norm * norm;
  const float trace = static_cast<float>(sxx) + syy;
  const float det = static_cast<float>(sxx) * syy - static_cast<float>(sxy) * sxy;
  return (det - kHarrisK * trace * trace) * norm4;
}

// Half-width of each row v = 0..radius of ORB's circular patch: the rounded circle on the rows
// below the diagonal, and on the others the mirror of the columns', so the patch is symmetric
// about its diagonals.
std::vector<int> disc_half_widths(int radius) {
  std::vector<int> width(radius + 2, 0);
  const float diagonal = radius * std::sqrt(2.f) / 2;
  const int rounded_up_to = static_cast<int>(std::floor(diagonal + 1));
  const int mirrored_from = static_cast<int>(std::ceil(diagonal));
  for (int v = 0; v <= rounded_up_to; ++v)
    width[v] = static_cast<int>(std::lrint(std::sqrt(double(radius) * radius - v * v)));
  for (int v = radius, column = 0; v >= mirrored_from; --v, ++column) {
    while (width[column] == width[column + 1]) ++column;
    width[v] = column;
  }
  width.resize(radius + 1);
  return width;
}

// ORB's orientation [deg] of pixel (x, y): the direction of the intensity centroid of the
// circular patch whose rows have the half-widths `disc` (integer moments, then OpenCV's
// fastAtan2, as its ORB computes it).
float centroid_angle(const cv::Mat &image, int x, int y, const std::vector<int> &disc) {
  const int radius = static_cast<int>(disc.size()) - 1;
  const int step = static_cast<int>(image.step);
  const uint8_t *centre = image.ptr<uint8_t>(y) + x;
  int m10 = 0, m01 = 0;
  for (int u = -radius; u <= radius; ++u) m10 += u * centre[u];
  for (int v = 1; v <= radius; ++v) {
    int below_minus_above = 0;
    for (int u = -disc[v]; u <= disc[v]; ++u) {
      const int below = centre[u + v * step], above = centre[u - v * step];
      below_minus_above += below - above;
      m10 += u * (below + above);
    }
    m01 += v * below_minus_above;
  }
  return cv::fastAtan2(static_cast<float>(m01), static_cast<float>(m10));
}

// A level image as a numpy array sharing its pixels (freed with the array).
py::array level_array(const cv::Mat &level) {
  auto *owner = new cv::Mat(level);
  py::capsule free_owner(owner, [](void *p) { delete static_cast<cv::Mat *>(p); });
  const std::vector<py::ssize_t> shape{level.rows, level.cols};
  const std::vector<py::ssize_t> strides{static_cast<py::ssize_t>(level.step[0]), 1};
  return py::array_t<uint8_t>(shape, strides, level.data, free_owner);
}

// The pyramid for Python: level 0 is the caller's own array.
py::list levels_list(const std::vector<cv::Mat> &levels, const py::array &input) {
  py::list out;
  out.append(input);
  for (size_t l = 1; l < levels.size(); ++l) out.append(level_array(levels[l]));
  return out;
}

// Indices (ascending) of the first n_keep keypoints in the order: rank within their (level,
// cell) by response (0 = the cell's best), then response, then index. Cells are cell_px[level]
// squares of level-0 pixels.
std::vector<int64_t> round_robin(const double *u, const double *v, const double *response,
                                 const int64_t *level, int64_t n,
                                 const std::vector<double> &cell_px, int64_t n_keep) {
  n_keep = std::max<int64_t>(0, std::min(n_keep, n));
  std::vector<int64_t> all(n);
  std::iota(all.begin(), all.end(), 0);
  if (n_keep == n) return all;
  if (n_keep == 0) return {};
  // Each keypoint's place in the order by response (ties: by index) makes every key below unique.
  std::vector<int64_t> by_response(all), place(n), cell(n), rank(n), by_cell(all), order(all);
  std::stable_sort(by_response.begin(), by_response.end(),
                   [&](int64_t a, int64_t b) { return response[a] > response[b]; });
  for (int64_t p = 0; p < n; ++p) place[by_response[p]] = p;
  const int64_t last = static_cast<int64_t>(cell_px.size()) - 1;
  for (int64_t k = 0; k < n; ++k) {
    const int64_t l = std::min(std::max<int64_t>(level[k], 0), last);
    const double size = cell_px[l];
    cell[k] = (l * 4096 + static_cast<int64_t>(std::floor(v[k] / size))) * 4096 +
              static_cast<int64_t>(std::floor(u[k] / size));
  }
  std::sort(by_cell.begin(), by_cell.end(), [&](int64_t a, int64_t b) {
    return cell[a] != cell[b] ? cell[a] < cell[b] : place[a] < place[b];
  });
  for (int64_t k = 0, first = 0; k < n; ++k) {
    if (k && cell[by_cell[k]] != cell[by_cell[k - 1]]) first = k;
    rank[by_cell[k]] = k - first;
  }
  std::nth_element(order.begin(), order.begin() + (n_keep - 1), order.end(),
                   [&](int64_t a, int64_t b) {
                     return rank[a] != rank[b] ? rank[a] < rank[b] : place[a] < place[b];
                   });
  order.resize(n_keep);
  std::sort(order.begin(), order.end());
  return order;
}

class OrbFrameExtractor {
 public:
  // wanted: keypoints per level; scales32: each level's scale as OpenCV's ORB has it
  // (features.orb_level_scales32); cell_px: each level's grid cell in level-0 pixels.
  OrbFrameExtractor(std::vector<int> wanted, std::vector<float> scales32,
                    std::vector<double> cell_px, double scale_factor, int edge_threshold_px,
                    int patch_px, int fast_threshold, int fast_threshold_first, int n_features,
                    int threads)
      : wanted_(std::move(wanted)),
        scales32_(std::move(scales32)),
        cell_px_(std::move(cell_px)),
        scale_factor_(scale_factor),
        edge_px_(edge_threshold_px),
        patch_px_(patch_px),
        fast_(fast_threshold),
        fast_first_(fast_threshold_first),
        n_features_(n_features),
        threads_(std::max(1, threads)),
        disc_(disc_half_widths(patch_px / 2)) {
    if (wanted_.empty() || scales32_.size() != wanted_.size() || cell_px_.size() != wanted_.size())
      throw std::invalid_argument("wanted, scales32 and cell_px need one entry per level (>= 1)");
    // The orientation and Harris score read the level image around each keypoint.
    if (patch_px_ < 8 || edge_px_ < patch_px_ / 2 + 1)
      throw std::invalid_argument("edge_threshold_px must exceed the patch radius (patch_px / 2)");
  }

  py::list extract(const py::list &arrays) {
    std::vector<py::array_t<uint8_t>> inputs;
    std::vector<Image> images(arrays.size());
    for (size_t i = 0; i < arrays.size(); ++i) {
      inputs.push_back(checked_gray(arrays[i], "image " + std::to_string(i)));
      Image &image = images[i];
      image.levels.resize(wanted_.size());
      image.levels[0] = wrap(inputs.back());
      image.found.resize(wanted_.size());
      image.chosen.resize(wanted_.size());
      image.described.resize(wanted_.size());
      image.descriptors.resize(wanted_.size());
    }
    {
      py::gil_scoped_release unlocked;
      extract_all(images);
    }
    py::list out;
    for (size_t i = 0; i < images.size(); ++i) out.append(result(images[i], inputs[i]));
    return out;
  }

 private:
  int n_levels() const { return static_cast<int>(wanted_.size()); }

  // A level's keypoint in level-0 pixels as OpenCV's ORB reports it (a float32 product).
  double level0(float coord, int level) const {
    return static_cast<double>(coord * scales32_[level]);
  }

  // The one-level ORB that describes a level's kept keypoints (it detects none: its FAST
  // threshold and Harris scoring play no part).
  cv::Ptr<cv::ORB> describer(int level) const {
    return cv::ORB::create(std::max(wanted_[level], 1), static_cast<float>(scale_factor_), 1,
                           edge_px_, 0, 2, cv::ORB::HARRIS_SCORE, patch_px_, fast_);
  }

  // One pass of items, handed out in order to whichever thread is free: each image's pyramid
  // and its levels largest first (a thread builds a pyramid while another detects level 0,
  // which needs none), then each image's bucketing once its levels are detected (a stereo
  // pair's two side by side), then its levels' descriptors once it is bucketed. An item waits
  // only for items before it, so the threads cannot deadlock.
  void extract_all(std::vector<Image> &images) {
    enum Stage { kPyramid, kDetect, kBucket, kDescribe };
    struct Item {
      int image, stage, level;
    };
    std::vector<Item> items;
    const int n = static_cast<int>(images.size());
    for (int i = 0; i < n; ++i) {
      items.push_back({i, kPyramid, 0});
      items.push_back({i, kDetect, 0});
      images[i].levels_pending = n_levels();
    }
    for (int l = 1; l < n_levels(); ++l)
      for (int i = 0; i < n; ++i) items.push_back({i, kDetect, l});
    for (int i = 0; i < n; ++i) items.push_back({i, kBucket, 0});
    for (int l = 0; l < n_levels(); ++l)
      for (int i = 0; i < n; ++i) items.push_back({i, kDescribe, l});
    std::mutex lock;
    std::condition_variable changed;
    auto wait_for = [&](auto ready) {
      std::unique_lock<std::mutex> hold(lock);
      changed.wait(hold, ready);
    };
    auto failed = [&](const Image &image) {
      std::lock_guard<std::mutex> hold(lock);
      return image.failed;
    };
    Workers::run(static_cast<int>(items.size()), threads_, [&](int k) {
      Image &image = images[items[k].image];
      const int level = items[k].level;
      bool ok = false;  // set when the item did its work; else later items of the image skip
      auto finish = [&](auto record) {
        {
          std::lock_guard<std::mutex> hold(lock);
          record();
          image.failed = image.failed || !ok;
        }
        changed.notify_all();
      };
      switch (items[k].stage) {
        case kPyramid: {
          auto done = on_exit([&] { finish([&] { image.pyramid_done = true; }); });
          build_levels(image.levels, scales32_);
          ok = true;
          return;
        }
        case kDetect: {
          auto done = on_exit([&] { finish([&] { --image.levels_pending; }); });
          if (level > 0) wait_for([&] { return image.pyramid_done; });
          if (!failed(image) && wanted_[level])
            image.found[level] = detect_level(image.levels[level], level);
          ok = true;
          return;
        }
        case kBucket: {
          auto done = on_exit([&] { finish([&] { image.bucketed = true; }); });
          wait_for([&] { return image.levels_pending == 0; });
          if (!failed(image)) bucket(image);
          ok = true;
          return;
        }
        default: {
          wait_for([&] { return image.bucketed; });
          auto &kps = image.chosen[level];
          if (failed(image) || kps.empty()) return;
          for (auto &kp : kps)
            kp.angle =
                centroid_angle(image.levels[level], cvRound(kp.pt.x), cvRound(kp.pt.y), disc_);
          describer(level)->compute(image.levels[level], kps, image.descriptors[level]);
          image.described[level] = kps;
        }
      }
    });
  }

  // At the first threshold when it finds as many keypoints as the level wants, else at the low
  // one (features.py's module docstring); the best by Harris score as ORB keeps them (unoriented).
  std::vector<cv::KeyPoint> detect_level(const cv::Mat &image, int level) const {
    const int wanted = wanted_[level];
    std::vector<cv::KeyPoint> kps;
    auto fast = [&](int threshold) {
      kps.clear();
      cv::FAST(image, kps, threshold, true);
      cv::KeyPointsFilter::runByImageBorder(kps, image.size(), edge_px_);
    };
    fast(std::max(fast_first_, fast_));
    if (fast_first_ > fast_ && static_cast<int>(kps.size()) < wanted) fast(fast_);
    cv::KeyPointsFilter::retainBest(kps, 2 * wanted);  // by FAST score
    for (auto &kp : kps) {
      kp.octave = 0;  // of the one-level ORB that describes them
      kp.size = static_cast<float>(patch_px_);
      kp.response = harris_score(image, cvRound(kp.pt.x), cvRound(kp.pt.y));
    }
    cv::KeyPointsFilter::retainBest(kps, wanted);
    return kps;
  }

  // Up to n_features keypoints by round_robin, kept in index order, per level.
  void bucket(Image &image) const {
    std::vector<double> u, v, response;
    std::vector<int64_t> level, index;
    for (int l = 0; l < n_levels(); ++l)
      for (size_t k = 0; k < image.found[l].size(); ++k) {
        const cv::KeyPoint &kp = image.found[l][k];
        u.push_back(level0(kp.pt.x, l));
        v.push_back(level0(kp.pt.y, l));
        response.push_back(static_cast<double>(kp.response));
        level.push_back(l);
        index.push_back(static_cast<int64_t>(k));
      }
    const auto keep = round_robin(u.data(), v.data(), response.data(), level.data(),
                                  static_cast<int64_t>(u.size()), cell_px_, n_features_);
    for (int64_t k : keep) image.chosen[level[k]].push_back(image.found[level[k]][index[k]]);
  }

  // (pt_px, angle_deg, octaves, descriptors, levels): pt_px as OpenCV's ORB reports a level's
  // keypoints in level-0 pixels (features.orb_level0_uv takes them to pixel centres).
  py::tuple result(const Image &image, const py::array_t<uint8_t> &input) const {
    py::ssize_t n = 0;
    for (int l = 0; l < n_levels(); ++l)
      if (!image.descriptors[l].empty()) n += static_cast<py::ssize_t>(image.described[l].size());
    py::array_t<double> pt({n, py::ssize_t(2)});
    py::array_t<float> angle(n);
    py::array_t<uint8_t> octaves(n), desc({n, py::ssize_t(32)});
    auto pt_ = pt.mutable_unchecked<2>();
    auto angle_ = angle.mutable_unchecked<1>();
    auto oct_ = octaves.mutable_unchecked<1>();
    uint8_t *desc_ = desc.mutable_data();
    py::ssize_t row = 0;
    for (int l = 0; l < n_levels(); ++l) {
      const cv::Mat &d = image.descriptors[l];
      if (d.empty()) continue;
      for (size_t k = 0; k < image.described[l].size(); ++k, ++row) {
        const cv::KeyPoint &kp = image.described[l][k];
        pt_(row, 0) = level0(kp.pt.x, l);
        pt_(row, 1) = level0(kp.pt.y, l);
        angle_(row) = kp.angle;
        oct_(row) = static_cast<uint8_t>(l);
        const uint8_t *bits = d.ptr<uint8_t>(static_cast<int>(k));
        std::copy(bits, bits + 32, desc_ + row * 32);
      }
    }
    return py::make_tuple(pt, angle, octaves, desc, levels_list(image.levels, input));
  }

  std::vector<int> wanted_;
  std::vector<float> scales32_;
  std::vector<double> cell_px_;
  double scale_factor_;
  int edge_px_, patch_px_, fast_, fast_first_, n_features_, threads_;
  std::vector<int> disc_;  // the orientation patch's row half-widths
};

// The image levels of one grey image (as OrbFrameExtractor.extract returns them).
py::list pyramid(const py::array &gray, const std::vector<float> &scales32) {
  if (scales32.empty()) throw std::invalid_argument("scales32: at least one level is needed");
  const auto input = checked_gray(gray, "gray");
  std::vector<cv::Mat> levels(scales32.size());
  levels[0] = wrap(input);
  {
    py::gil_scoped_release unlocked;
    build_levels(levels, scales32);
  }
  return levels_list(levels, input);
}

template <typename T>
using Column = py::array_t<T, py::array::c_style | py::array::forcecast>;

py::array_t<int64_t> round_robin_array(const Column<double> &u, const Column<double> &v,
                                       const Column<double> &response,
                                       const Column<int64_t> &octave,
                                       const std::vector<double> &cell_px, int64_t n_keep) {
  const py::ssize_t n = u.size();
  if (v.size() != n || response.size() != n || octave.size() != n)
    throw std::invalid_argument("u, v, response and octave need one entry per keypoint");
  if (cell_px.empty()) throw std::invalid_argument("cell_px: at least one level is needed");
  const auto keep =
      round_robin(u.data(), v.data(), response.data(), octave.data(), n, cell_px, n_keep);
  py::array_t<int64_t> out(static_cast<py::ssize_t>(keep.size()));
  std::copy(keep.begin(), keep.end(), out.mutable_data());
  return out;
}

}  // namespace

PYBIND11_MODULE(_orb_native, m) {
  m.doc() = "Grid-bucketed ORB extraction of a frame's images (coop_slam.vo.features drives it).";
  py::class_<OrbFrameExtractor>(m, "OrbFrameExtractor")
      .def(py::init<std::vector<int>, std::vector<float>, std::vector<double>, double, int, int,
                    int, int, int, int>(),
           py::arg("wanted"), py::arg("scales32"), py::arg("cell_px"), py::arg("scale_factor"),
           py::arg("edge_threshold_px"), py::arg("patch_px"), py::arg("fast_threshold"),
           py::arg("fast_threshold_first"), py::arg("n_features"), py::arg("threads"))
      .def("extract", &OrbFrameExtractor::extract, py::arg("images"),
           "[(pt_px, angle_deg, octaves, descriptors, levels)] of each image");
  m.def("pyramid", &pyramid, py::arg("gray"), py::arg("scales32"));
  m.def("round_robin", &round_robin_array, py::arg("u"), py::arg("v"), py::arg("response"),
        py::arg("octave"), py::arg("cell_px"), py::arg("n_keep"));
}
