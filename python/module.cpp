// _ag2gs: the compiled half of the Python module (python/ag2gs/ is the other
// half). It holds what must stay in memory between calls (a scene, a model on
// the device, a query engine) and runs the program's commands in this process
// (cli/commands.h run_command), so a model trained or rendered from Python
// has the bits the program would write. The GIL is released around device
// work; the training callback takes it back for each call.
#include <pybind11/functional.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>
#include <spdlog/spdlog.h>

#include <cmath>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "cli/commands.h"
#include "cli/model_render.h"
#include "cli/run_guard.h"
#include "host/device/cl_runtime.h"
#include "host/io/colmap_reader.h"
#include "host/io/image_io.h"
#include "host/scene/scene.h"
#include "queries/query.h"

namespace py = pybind11;
namespace fs = std::filesystem;
using namespace ag2gs;
using namespace ag2gs::cli;

namespace {

// A row-major float array of `shape` holding `values` (copied: NumPy owns it).
template <typename T>
py::array_t<T> to_array(const std::vector<T>& values, std::vector<py::ssize_t> shape) {
  py::array_t<T> a(shape);
  std::copy(values.begin(), values.end(), a.mutable_data());
  return a;
}

// [H,W,3] uint8 from floats in [0,1] read from an 8-bit file (exact).
py::array_t<uint8_t> to_uint8(const std::vector<float>& rgb, int width, int height) {
  py::array_t<uint8_t> a({static_cast<py::ssize_t>(height), static_cast<py::ssize_t>(width), py::ssize_t{3}});
  uint8_t* p = a.mutable_data();
  for (size_t i = 0; i < rgb.size(); ++i)
    p[i] = static_cast<uint8_t>(std::lround(std::min(1.f, std::max(0.f, rgb[i])) * 255.f));
  return a;
}

py::dict camera_dict(const Camera& c) {
  py::dict d;
  d["width"] = c.width;
  d["height"] = c.height;
  d["fx"] = c.fx;
  d["fy"] = c.fy;
  d["cx"] = c.cx;
  d["cy"] = c.cy;
  std::vector<double> R(9), t(3);
  for (int r = 0; r < 3; ++r) {
    for (int k = 0; k < 3; ++k) R[3 * r + k] = c.R(r, k);
    t[r] = c.t(r);
  }
  d["R"] = to_array(R, {3, 3});
  d["t"] = to_array(t, {3});
  d["name"] = c.name;
  return d;
}

// The Python Camera's fields (python/ag2gs/__init__.py) as a Camera.
Camera camera_from(const py::object& o) {
  Camera c;
  c.width = o.attr("width").cast<int>();
  c.height = o.attr("height").cast<int>();
  c.fx = o.attr("fx").cast<double>();
  c.fy = o.attr("fy").cast<double>();
  c.cx = o.attr("cx").cast<double>();
  c.cy = o.attr("cy").cast<double>();
  c.name = o.attr("name").cast<std::string>();
  auto R = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(o.attr("R"));
  auto t = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(o.attr("t"));
  if (!R || R.size() != 9) throw std::invalid_argument("camera.R must be a 3x3 rotation (world to camera)");
  if (!t || t.size() != 3) throw std::invalid_argument("camera.t must be 3 numbers (world to camera)");
  for (int r = 0; r < 3; ++r) {
    for (int k = 0; k < 3; ++k) c.R(r, k) = R.data()[3 * r + k];
    c.t(r) = t.data()[r];
  }
  // Camera::validate refuses sizes, intrinsics and an R that is not a rotation.
  c.validate();
  return c;
}

// A scene folder opened once: its views' cameras and images.
class PyScene {
 public:
  PyScene(const std::string& dir, int resolution, bool eval, const std::string& sparse,
          const std::vector<std::string>& test_images) {
    SceneOptions o;
    o.resolution = resolution;
    o.eval = eval;
    o.sparse = sparse;
    o.test_images = test_images;
    scene_ = Scene::open(dir, o);
  }
  std::string dir() const { return scene_->dir(); }
  py::list views() const {
    py::list out;
    for (const SceneView& v : scene_->views()) {
      py::dict d;
      d["index"] = v.index;
      d["name"] = v.name;
      d["stem"] = v.stem;
      d["test"] = v.test;
      d["camera"] = camera_dict(v.camera);
      out.append(d);
    }
    return out;
  }
  // [H,W,3] uint8: the image as read (floats in [0,1] from 8-bit files).
  py::array_t<uint8_t> image(int view) {
    if (view < 0 || view >= static_cast<int>(scene_->views().size()))
      throw py::index_error("view " + std::to_string(view) + " out of range");
    std::shared_ptr<const Image> im;
    {
      py::gil_scoped_release release;
      im = scene_->image(view);
    }
    return to_uint8(im->rgb, im->width, im->height);
  }
  int semantics() const { return static_cast<int>(scene_->semantics()); }
  const Scene& scene() const { return *scene_; }

 private:
  std::unique_ptr<Scene> scene_;
};

// A model on the device, rendered view by view (cli/model_render.h).
class PyRenderer {
 public:
  PyRenderer(const std::string& model, const std::string& ply, const std::vector<std::string>& outputs,
             std::optional<std::array<float, 3>> background, int device)
      : rt_(device) {
    ModelRenderOptions o;
    o.model = model;
    o.ply = ply;
    o.outputs = outputs;
    o.background = background;
    outputs_ = outputs;
    py::gil_scoped_release release;
    render_ = std::make_unique<ModelRender>(rt_, o);
  }
  py::dict render(const py::object& camera) {
    const Camera cam = camera_from(camera);
    ModelFrame f;
    {
      py::gil_scoped_release release;
      f = render_->render(cam);
    }
    const py::ssize_t h = f.height, w = f.width;
    py::dict d;
    for (const std::string& o : outputs_) {
      if (o == "rgb") d["rgb"] = to_array(f.rgb, {h, w, 3});
      if (o == "depth") d["depth"] = to_array(f.depth, {h, w});
      if (o == "alpha") d["alpha"] = to_array(f.alpha, {h, w});
      if (o == "feature") d["feature"] = to_array(f.feature, {h, w, 3});
      if (o == "instance") d["instance"] = to_array(f.instance, {h, w});
    }
    return d;
  }
  size_t gaussians() const { return render_->gaussians(); }
  bool has_sky() const { return render_->has_sky(); }
  std::string device() const { return rt_.info().name; }

 private:
  Runtime rt_;
  std::vector<std::string> outputs_;
  std::unique_ptr<ModelRender> render_;
};

// A model, its scene and the query engine, kept for any number of queries:
// the same steps as `ag2gs query` (cli/cmd_query.cpp) without its files.
class PyQuery {
 public:
  PyQuery(const std::string& model_dir, PyScene& scene, bool with_language, int device)
      : scene_(scene), rt_(device), tm_(load_trained_model(model_dir, with_language)) {
    engine_ = std::make_unique<QueryEngine>(rt_, tm_.model, config_);
    if (with_language) engine_->set_language(tm_.clustering, tm_.language);
  }
  // Returns (anchor ids, the record `query` writes into selection.json).
  std::pair<std::vector<int32_t>, std::string> run(const std::string& view, const std::string& click,
                                                   const std::string& text, const std::string& vocab,
                                                   const std::string& text_embedding, const std::string& click_by) {
    QueryRequest r;
    r.view = view;
    r.click = click;
    r.text = text;
    r.vocab = vocab;
    r.text_embedding = text_embedding;
    r.click_by = click_by;
    check_query_request(r);
    py::gil_scoped_release release;
    nlohmann::json j;
    std::vector<float> embedding;
    if (r.by_text()) embedding = load_query_embedding(r, tm_.file, tm_.language.dim);
    if (r.by_click()) prepare_click(*engine_, r.click_by, tm_.archive.meta, scene_.scene(), &j);
    double ms = 0;
    const int resolution = scene_.scene().options().resolution;
    std::vector<int32_t> selected =
        run_query(*engine_, scene_.scene(), r, embedding, resolution, config_.text_margin, j, &ms);
    j["anchors"] = selected;
    j["query_ms"] = ms;
    return {selected, j.dump()};
  }
  // [H,W] bool: the selection's pixels in `camera`, as `query` writes its masks.
  py::array_t<bool> mask(const py::object& camera, const std::vector<int32_t>& anchors) {
    const Camera cam = camera_from(camera);
    for (int32_t a : anchors)
      if (a < 0 || static_cast<size_t>(a) >= tm_.model.size())
        throw py::value_error("anchor " + std::to_string(a) + " is not one of the model's " +
                              std::to_string(tm_.model.size()) + " anchors");
    std::vector<uint8_t> m;
    {
      py::gil_scoped_release release;
      m = engine_->mask(cam, anchors);
    }
    py::array_t<bool> a({static_cast<py::ssize_t>(cam.height), static_cast<py::ssize_t>(cam.width)});
    bool* p = a.mutable_data();
    for (size_t i = 0; i < m.size(); ++i) p[i] = m[i] != 0;
    return a;
  }
  size_t anchors() const { return tm_.model.size(); }
  int resolution() const { return tm_.resolution; }

 private:
  PyScene& scene_;
  Runtime rt_;
  TrainedModel tm_;
  QueryConfig config_;
  std::unique_ptr<QueryEngine> engine_;
};

// Runs one command line; `callback(progress dict)` after each training
// iteration may return False to stop. Returns 0, or the status a signal or
// the callback's stop ended the run with (its checkpoint written).
int run(const std::vector<std::string>& args, py::object callback) {
  std::optional<py::error_already_set> callback_error;
  if (!callback.is_none()) {
    set_train_progress_hook([&](const nlohmann::json& progress) {
      py::gil_scoped_acquire acquire;
      if (callback_error) return false;
      try {
        py::object d = py::module_::import("json").attr("loads")(progress.dump());
        py::object r = callback(d);
        return !(r.is(py::bool_(false)));
      } catch (py::error_already_set& e) {
        callback_error = std::move(e);
        return false;
      }
    });
  }
  struct Unhook {
    ~Unhook() { set_train_progress_hook({}); }
  } unhook;
  int status = 0;
  {
    py::gil_scoped_release release;
    try {
      run_command(args);
    } catch (const StoppedAfterSaving& e) {
      status = e.exit_code;
    }
  }
  if (callback_error) throw std::move(*callback_error);
  return status;
}

// [H,W,3] uint8: an image file as the program reads it.
py::array_t<uint8_t> read_image(const std::string& path) {
  int w = 0, h = 0;
  const std::vector<float> rgb = read_rgb(path, w, h);
  return to_uint8(rgb, w, h);
}

py::list devices() {
  py::list out;
  for (const DeviceInfo& d : list_devices()) {
    py::dict x;
    x["index"] = d.index;
    x["name"] = d.name;
    x["platform"] = d.platform;
    x["vendor"] = d.vendor;
    x["type"] = d.is_gpu ? "gpu" : d.is_cpu ? "cpu" : "other";
    x["compute_units"] = d.compute_units;
    x["global_mem"] = d.global_mem;
    out.append(x);
  }
  return out;
}

}  // namespace

PYBIND11_MODULE(_ag2gs, m) {
  m.doc() = "ag2gs's compiled core; use the ag2gs package.";
  // Outside commands (which log as the program does) only warnings and
  // errors are printed, in the program's format.
  spdlog::set_pattern("%^%l%$: %v");
  spdlog::set_level(spdlog::level::warn);
  m.def(
      "set_log_level",
      [](const std::string& level) {
        const spdlog::level::level_enum l = spdlog::level::from_str(level);
        if (l == spdlog::level::off && level != "off")
          throw std::invalid_argument("log level '" + level + "': use debug, info, warn, error or off");
        spdlog::set_level(l);
      },
      py::arg("level"), "The level of messages outside commands: debug, info, warn (default), error or off.");
  // A missing file or folder is a FileNotFoundError carrying the program's
  // message; other errors keep their kinds (ValueError for bad arguments).
  py::register_exception_translator([](std::exception_ptr p) {
    try {
      if (p) std::rethrow_exception(p);
    } catch (const py::builtin_exception& e) {  // value_error, index_error, ...: their own kinds
      e.set_error();
    } catch (const std::runtime_error& e) {
      const std::string w = e.what();
      if (w.find("no such") != std::string::npos || w.find("does not exist") != std::string::npos ||
          w.find("not found") != std::string::npos || w.find("No such") != std::string::npos)
        PyErr_SetString(PyExc_FileNotFoundError, w.c_str());
      else
        PyErr_SetString(PyExc_RuntimeError, w.c_str());
    }
  });
  m.def(
      "scale_camera", [](const py::object& c, int factor) { return camera_dict(scale_camera(camera_from(c), factor)); },
      py::arg("camera"), py::arg("factor"), "The camera at 1/factor resolution, as -r scales it.");
  m.def(
      "resize_camera",
      [](const py::object& c, int width, int height) {
        return camera_dict(resize_camera(camera_from(c), width, height));
      },
      py::arg("camera"), py::arg("width"), py::arg("height"), "The same view at another image size.");
  m.def("read_image", &read_image, py::arg("path"), "An image file as HxWx3 uint8 RGB.");
  m.def("devices", &devices, "The OpenCL devices, as `ag2gs devices` lists them.");
  m.def("command_help", &command_help, py::arg("command"), "`ag2gs COMMAND --help`'s text.");
  m.def("run", &run, py::arg("args"), py::arg("callback") = py::none(),
        "Runs one ag2gs command line in this process; returns 0 or a stopped run's status.");
  py::class_<PyScene>(m, "_Scene")
      .def(py::init<const std::string&, int, bool, const std::string&, const std::vector<std::string>&>(),
           py::arg("dir"), py::arg("resolution"), py::arg("eval"), py::arg("sparse"), py::arg("test_images"))
      .def_property_readonly("dir", &PyScene::dir)
      .def("views", &PyScene::views)
      .def("image", &PyScene::image)
      .def_property_readonly("semantics", &PyScene::semantics);
  py::class_<PyRenderer>(m, "_Renderer")
      .def(py::init<const std::string&, const std::string&, const std::vector<std::string>&,
                    std::optional<std::array<float, 3>>, int>(),
           py::arg("model"), py::arg("ply"), py::arg("outputs"), py::arg("background"), py::arg("device"))
      .def("render", &PyRenderer::render)
      .def_property_readonly("gaussians", &PyRenderer::gaussians)
      .def_property_readonly("has_sky", &PyRenderer::has_sky)
      .def_property_readonly("device", &PyRenderer::device);
  py::class_<PyQuery>(m, "_Query")
      .def(py::init<const std::string&, PyScene&, bool, int>(), py::arg("model"), py::arg("scene"),
           py::arg("with_language"), py::arg("device"), py::keep_alive<1, 3>())
      .def("run", &PyQuery::run)
      .def("mask", &PyQuery::mask)
      .def_property_readonly("anchors", &PyQuery::anchors)
      .def_property_readonly("resolution", &PyQuery::resolution);
}
