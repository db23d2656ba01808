#include "cli/commands.h"

#include <spdlog/spdlog.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <map>
#include <memory>
#include <sstream>

#include "host/cl_runtime.h"
#include "host/colmap_reader.h"
#include "host/image_io.h"
#include "host/ply_io.h"
#include "host/renderer.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {

namespace {

std::map<CLI::App*, std::function<void()>>& actions() {
  static std::map<CLI::App*, std::function<void()>> a;
  return a;
}

std::string human_bytes(uint64_t b) {
  char buf[32];
  if (b >= (1ull << 30))
    std::snprintf(buf, sizeof buf, "%.1f GiB", b / double(1ull << 30));
  else if (b >= (1ull << 20))
    std::snprintf(buf, sizeof buf, "%.1f MiB", b / double(1ull << 20));
  else
    std::snprintf(buf, sizeof buf, "%.0f KiB", b / 1024.0);
  return buf;
}

// ------------------------------------------------------------------ devices
void cmd_devices(const GlobalOptions& global) {
  auto devices = list_devices();
  if (devices.empty()) {
    resolve_device_index(-1, devices);  // throws the install hint
  }
  int def = default_device_index(devices);
  int selected = resolve_device_index(global.device, devices);
  for (auto& d : devices) {
    std::printf("[%d]%s %s\n", d.index,
                d.index == selected ? (d.index == def ? " (default, selected)" : " (selected)")
                                    : (d.index == def ? " (default)" : ""),
                d.name.c_str());
    std::printf("    platform: %s\n", d.platform.c_str());
    std::printf("    type: %s   compute units: %u   global memory: %s   local memory: %s\n",
                d.is_gpu   ? "GPU"
                : d.is_cpu ? "CPU"
                           : "other",
                d.compute_units, human_bytes(d.global_mem).c_str(), human_bytes(d.local_mem).c_str());
    std::printf("    fp64: %s   max work-group: %zu   version: %s   driver: %s\n", d.fp64 ? "yes" : "no",
                d.max_work_group, d.version.c_str(), d.driver.c_str());
  }
}

// ------------------------------------------------------------------ render
struct RenderArgs {
  std::string ply, scene, out, views, bg = "0,0,0", sparse = "sparse/0";
  int resolution = 1;
  bool extras = false;
};

std::array<float, 3> parse_rgb(const std::string& s) {
  std::array<float, 3> v{};
  std::stringstream ss(s);
  std::string item;
  int i = 0;
  while (std::getline(ss, item, ',')) {
    if (i >= 3) break;
    try {
      size_t used = 0;
      v[i] = std::stof(item, &used);
      if (used != item.size()) throw std::invalid_argument(item);
    } catch (const std::exception&) {
      throw std::invalid_argument("--bg '" + s + "': '" + item +
                                  "' is not a number; expected R,G,B in [0,1], e.g. 1,1,1");
    }
    ++i;
  }
  if (i != 3) throw std::invalid_argument("--bg '" + s + "': expected three numbers R,G,B in [0,1], e.g. 1,1,1");
  return v;
}

void cmd_render(const GlobalOptions& global, const RenderArgs& a) {
  if (a.resolution < 1) throw std::invalid_argument("-r must be >= 1 (it divides the camera resolution)");
  RenderSettings settings;
  settings.background = parse_rgb(a.bg);
  GaussianSet set = read_ply(a.ply);
  fs::path sparse = fs::path(a.scene) / a.sparse;
  if (!fs::is_directory(sparse))
    throw std::runtime_error(sparse.string() + " is not a directory; --scene must hold a COLMAP model in " + a.sparse +
                             "/ (cameras, images, points3D as .bin or .txt)");
  ColmapModel model = read_colmap_model(sparse.string());
  std::vector<Camera> cams =
      a.views.empty() ? model.cameras_for_images : select_views(model.cameras_for_images, a.views);
  if (cams.empty()) throw std::runtime_error(sparse.string() + " has no registered images to render");

  Runtime rt(global.device);
  spdlog::info("device [{}] {}; {} Gaussians (SH degree {}), {} views", rt.info().index, rt.info().name, set.size(),
               set.sh_degree, cams.size());
  Renderer renderer(rt);
  DeviceGaussians dg(rt);
  dg.upload(set);
  fs::path out_dir(a.out);
  fs::create_directories(out_dir / "rgb");
  if (a.extras) {
    fs::create_directories(out_dir / "depth");
    fs::create_directories(out_dir / "alpha");
  }
  auto t0 = std::chrono::steady_clock::now();
  for (size_t i = 0; i < cams.size(); ++i) {
    Camera cam = scale_camera(cams[i], a.resolution);
    renderer.forward(dg, cam, settings);
    RenderOutput out = renderer.download_output();
    std::string stem = fs::path(cam.name).stem().string();
    write_rgb_png((out_dir / "rgb" / (stem + ".png")).string(), out.rgb, out.width, out.height);
    if (a.extras) {
      // Mean depth (metres, 16-bit millimetres) and alpha (16-bit).
      std::vector<float> depth(out.depth.size());
      for (size_t p = 0; p < depth.size(); ++p) depth[p] = out.alpha[p] > 1e-6f ? out.depth[p] / out.alpha[p] : 0.f;
      write_gray16_png((out_dir / "depth" / (stem + ".png")).string(), depth, out.width, out.height, 1000.f);
      write_gray16_png((out_dir / "alpha" / (stem + ".png")).string(), out.alpha, out.width, out.height, 65535.f);
    }
    double el = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    double eta = el / (i + 1) * (cams.size() - i - 1);
    spdlog::info("[{}/{}] {} {}x{}  {} intersections  {:.1f} s elapsed, ETA {:.1f} s", i + 1, cams.size(), cam.name,
                 out.width, out.height, renderer.stats().n_intersections, el, eta);
  }
  spdlog::info("wrote {} images to {}", cams.size(), (out_dir / "rgb").string());
}

}  // namespace

void register_commands(CLI::App& app, GlobalOptions& global) {
  auto* dev = app.add_subcommand("devices", "List OpenCL platforms and devices");
  actions()[dev] = [&global] { cmd_devices(global); };

  auto ra = std::make_shared<RenderArgs>();
  auto* render = app.add_subcommand("render", "Render a 3DGS .ply from a scene's COLMAP cameras");
  render->add_option("--ply", ra->ply, "Gaussians in the standard 3DGS point_cloud.ply layout")->required();
  render->add_option("--scene", ra->scene, "Scene directory holding sparse/0/ (COLMAP model)")->required();
  render->add_option("-o,--out", ra->out, "Output directory; images go to OUT/rgb/<image stem>.png")->required();
  render->add_option("--views", ra->views, "Comma-separated image names or stems (default: all)");
  render->add_option("--bg", ra->bg, "Background colour R,G,B in [0,1] (default 0,0,0)");
  render->add_option("-r,--resolution", ra->resolution, "Divide the camera resolution by R (default 1)");
  render->add_option("--sparse", ra->sparse, "COLMAP model folder inside the scene (default sparse/0)");
  render->add_flag("--extras", ra->extras, "Also write OUT/depth (16-bit mm) and OUT/alpha (16-bit) PNGs");
  actions()[render] = [&global, ra] { cmd_render(global, *ra); };

  register_scene_commands(app, global);
  register_synth(app, global);
  register_train(app, global);
}

void set_action(CLI::App* sub, std::function<void()> action) {
  actions()[sub] = std::move(action);
}

int run_selected(CLI::App& app, const GlobalOptions& global) {
  spdlog::set_level(global.verbose ? spdlog::level::debug : global.quiet ? spdlog::level::warn : spdlog::level::info);
  spdlog::set_pattern("%^%l%$: %v");
  for (auto* sub : app.get_subcommands()) {
    auto it = actions().find(sub);
    if (it == actions().end()) continue;
    try {
      it->second();
      return 0;
    } catch (const std::exception& e) {
      std::fprintf(stderr, "ag2gs %s: error: %s\n", sub->get_name().c_str(), e.what());
      return 1;
    }
  }
  return 2;
}

}  // namespace ag2gs::cli
