#include "train/checkpoint.h"

#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <stdexcept>
#include <system_error>

#include "host/core/counter_rng.h"
#include "host/io/atomic_file.h"
#include "host/io/json_input.h"
#include "host/io/model_io.h"
#include "host/io/model_ply.h"
#include "host/io/ply_io.h"
#include "train/trainer.h"

namespace fs = std::filesystem;

namespace ag2gs {

namespace {

// Every leaf of a JSON object as "a.b.c" -> value.
void flatten(const nlohmann::json& j, const std::string& prefix, std::map<std::string, nlohmann::json>* out) {
  if (j.is_object()) {
    for (auto it = j.begin(); it != j.end(); ++it)
      flatten(it.value(), prefix.empty() ? it.key() : prefix + "." + it.key(), out);
  } else {
    (*out)[prefix] = j;
  }
}

}  // namespace

std::vector<std::string> config_differences(const nlohmann::json& a, const nlohmann::json& b) {
  std::map<std::string, nlohmann::json> fa, fb;
  flatten(a, "", &fa);
  flatten(b, "", &fb);
  std::vector<std::string> out;
  for (const auto& [k, v] : fa) {
    auto it = fb.find(k);
    if (it == fb.end())
      out.push_back(k + " (" + v.dump() + " vs missing)");
    else if (it->second != v)
      out.push_back(k + " (" + v.dump() + " vs " + it->second.dump() + ")");
  }
  for (const auto& [k, v] : fb)
    if (!fa.count(k)) out.push_back(k + " (missing vs " + v.dump() + ")");
  return out;
}

void check_model_dir_writable(const std::string& dir) {
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec || !fs::is_directory(dir))
    throw std::runtime_error("model directory " + dir + " cannot be created" + (ec ? ": " + ec.message() : "") +
                             "; choose another -o");
  const fs::path probe = fs::path(dir) / (".ag2gs_write_test." + std::to_string(::getpid()));
  bool ok = false;
  {
    std::ofstream f(probe, std::ios::binary);
    if (f) {
      f << "ok";
      f.close();
      ok = static_cast<bool>(f);
    }
  }
  fs::remove(probe, ec);
  if (!ok) throw std::runtime_error("model directory " + dir + " is not writable; choose another -o");
}

void write_json_atomic(const std::string& path, const nlohmann::json& doc) {
  AtomicFile f(path);
  f.write(doc.dump(2) + "\n");
  f.commit();
}

std::string Trainer::checkpoint_path(const std::string& model_dir) {
  return (fs::path(model_dir) / "checkpoint.ag2gs").string();
}

nlohmann::json scene_fingerprint(const Scene& scene, size_t train_views) {
  // Cameras hashed through their printed values (exact: %a is lossless).
  std::string cams;
  char buf[512];
  for (const SceneView& v : scene.views()) {
    const Camera& c = v.camera;
    std::snprintf(buf, sizeof buf, "%s %d %d %a %a %a %a %d|", v.name.c_str(), c.width, c.height, c.fx, c.fy, c.cx,
                  c.cy, v.test ? 1 : 0);
    cams += buf;
    for (int i = 0; i < 3; ++i) {
      std::snprintf(buf, sizeof buf, "%a %a %a %a|", c.R(i, 0), c.R(i, 1), c.R(i, 2), c.t(i));
      cams += buf;
    }
  }
  std::vector<double> pts;
  pts.reserve(scene.points().size() * 3);
  for (const Eigen::Vector3d& p : scene.points()) pts.insert(pts.end(), {p.x(), p.y(), p.z()});
  char hex[2][20];
  std::snprintf(hex[0], sizeof hex[0], "%016llx", static_cast<unsigned long long>(fnv1a64(cams.data(), cams.size())));
  std::snprintf(hex[1], sizeof hex[1], "%016llx",
                static_cast<unsigned long long>(fnv1a64(pts.data(), pts.size() * sizeof(double))));
  return {{"views", scene.views().size()},
          {"train_views", train_views},
          {"resolution", scene.options().resolution},
          {"eval_split", scene.options().eval},
          {"cameras_fnv1a64", hex[0]},
          {"points", scene.points().size()},
          {"points_fnv1a64", hex[1]}};
}

nlohmann::json Trainer::scene_fingerprint() const {
  return ag2gs::scene_fingerprint(scene_, train_views_.size());
}

void Trainer::save_checkpoint(const std::string& model_dir) {
  const AnchorModel& m = model();
  ModelArchive archive;
  m.to_archive(archive);
  const nlohmann::json groups = groups_->to_archive(archive);
  if (sky_.enabled()) sky_to_archive(archive, sky_.download());
  const GrowthStatsHost gs = growth_.download();
  archive.put("growth/grad_sum", gs.grad_sum);
  archive.put("growth/count", gs.count);
  archive.put("growth/last_seen", gs.last_seen);
  if (graph_ready_) graph_.to_archive(archive);
  archive.meta["checkpoint"] = {{"iteration", iteration_},
                                {"config", config_.to_json()},
                                {"scene", scene_fingerprint()},
                                {"scene_dir", scene_.dir()},
                                {"adam", groups},
                                {"growth", {{"steps", gs.steps}, {"step", gs.step}}}};
  if (!run_record_.is_null()) archive.meta["checkpoint"]["run"] = run_record_;
  fs::create_directories(model_dir);
  write_model_archive(checkpoint_path(model_dir), archive);
}

void Trainer::resume(const std::string& model_dir) {
  const std::string path = checkpoint_path(model_dir);
  if (!fs::exists(path))
    throw std::runtime_error("no checkpoint " + path + " to resume from; train without --resume to start afresh");
  const ModelArchive archive = read_model_archive(path);
  auto fail = [&](const std::string& what) { throw std::runtime_error("checkpoint " + path + ": " + what); };
  if (!archive.meta.contains("checkpoint")) fail("no training state (not written by ag2gs train)");
  const nlohmann::json& ck = archive.meta["checkpoint"];
  try {
    const std::vector<std::string> scene_diff = config_differences(ck.at("scene"), scene_fingerprint());
    if (!scene_diff.empty()) {
      std::string list;
      for (const std::string& d : scene_diff) list += "\n  " + d;
      fail("written for another scene (" + ck.value("scene_dir", std::string("?")) +
           ") or resolution/split; checkpoint vs now:" + list);
    }
    const std::vector<std::string> config_diff = config_differences(ck.at("config"), config_.to_json());
    if (!config_diff.empty()) {
      std::string list;
      for (const std::string& d : config_diff) list += "\n  " + d;
      fail("written with another training config; checkpoint vs now:" + list);
    }
    const int iteration = ck.at("iteration").get<int>();
    if (iteration < 0 || iteration > config_.total_iterations())
      fail("iteration " + std::to_string(iteration) + " is outside the run's 0.." +
           std::to_string(config_.total_iterations()));
    AnchorModel m = AnchorModel::from_archive(archive);
    AnchorGraph graph;
    const bool has_graph = AnchorGraph::in_archive(archive);
    if (has_graph) {
      graph = AnchorGraph::from_archive(archive);
      if (!graph.matches(m)) fail("its anchor graph does not describe its anchors; train stage 2 afresh");
    }
    const int64_t n = static_cast<int64_t>(m.gaussians());
    std::unique_ptr<ParamGroups> groups =
        ParamGroups::from_archive(rt_, group_specs(), archive, ck.at("adam"), m.gaussians(), m.size());
    std::optional<std::vector<float>> sky = sky_from_archive(archive);
    if (sky_.enabled() != sky.has_value() || (sky && sky_degree_for(sky->size()) != config_.sky_degree))
      fail("its sky does not match the config's sky_degree " + std::to_string(config_.sky_degree));
    GrowthStatsHost gs;
    gs.grad_sum = archive.get<float>("growth/grad_sum", {n});
    gs.count = archive.get<int32_t>("growth/count", {n});
    gs.last_seen = archive.get<int32_t>("growth/last_seen", {n});
    gs.steps = ck.at("growth").at("steps").get<int>();
    gs.step = ck.at("growth").at("step").get<int>();
    // Everything read: now replace the state.
    model_ = std::move(m);
    anchors_.upload(model_);
    host_stale_ = false;
    groups_ = std::move(groups);
    if (sky) sky_.set(config_.sky_degree, *sky);
    growth_.set_config(config_.growth_config(train_views_.size()));
    growth_.restore(gs);
    iteration_ = iteration;
    graph_ready_ = false;
    if (has_graph && iteration >= config_.iterations) {
      graph_ = std::move(graph);
      prop_.set_graph(graph_);
      graph_ready_ = true;
    }
  } catch (const nlohmann::json::exception& e) {
    fail(std::string("bad training state: ") + json_error_text(e));
  } catch (const std::invalid_argument& e) {
    fail(e.what());
  }
}

ModelArchive Trainer::model_archive() {
  const AnchorModel& m = model();
  ModelArchive archive;
  m.to_archive(archive);
  if (graph_ready_) graph_.to_archive(archive);
  if (sky_.enabled()) sky_to_archive(archive, sky_.download());
  archive.meta["train"] = {{"stage", iteration_ > config_.iterations ? 2 : 1},
                           {"iteration", iteration_},
                           {"seed", config_.seed},
                           {"active_sh_degree", active_sh_degree()},
                           {"scene", scene_.dir()},
                           {"resolution", scene_.options().resolution},
                           {"eval_split", scene_.options().eval},
                           {"config", config_.to_json()}};
  return archive;
}

void Trainer::save(const std::string& model_dir) {
  save_checkpoint(model_dir);
  const AnchorModel& m = model();
  const ModelArchive archive = model_archive();
  fs::create_directories(model_dir);
  write_model_archive((fs::path(model_dir) / "model.ag2gs").string(), archive);
  // point_cloud.ply carries the sky too, so other viewers show what we render.
  std::optional<std::vector<float>> sky;
  if (sky_.enabled()) sky = sky_.download();
  std::vector<Camera> cameras;
  for (const auto& v : scene_.views()) cameras.push_back(v.camera);
  last_ply_ = write_model_plys(model_dir, expand_reference(m, active_sh_degree()), sky, cameras);
}

}  // namespace ag2gs
