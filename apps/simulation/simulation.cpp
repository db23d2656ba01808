#include "apps/simulation/simulation.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <map>
#include <stdexcept>

#include "host/core/quantile.h"
#include "host/scene/scene_up.h"

namespace ag2gs {

namespace {

const std::map<std::string, std::string> kNoDefines;

// An object stands on the scene's main plane when its lowest Gaussians lie
// within this fraction of its height from it.
constexpr double kOnFloor = 0.1;

void check_material(const MpmMaterial& m, const std::string& flags) {
  if (!(m.E > 0) || !std::isfinite(m.E)) throw std::invalid_argument(flags + ": E must be a finite number > 0");
  if (!(m.nu > -1 && m.nu < 0.5)) throw std::invalid_argument(flags + ": nu must lie in (-1, 0.5)");
  if (!(m.density > 0) || !std::isfinite(m.density))
    throw std::invalid_argument(flags + ": the density must be a finite number > 0");
}

}  // namespace

void SimulationSettings::validate() const {
  check_material(object, "--E / --nu / --density");
  check_material(background, "--background-E / --background-nu");
  if (grid < 16 || grid > 512) throw std::invalid_argument("--grid must lie in 16..512 cells");
  if (!(frame_time > 0) || !std::isfinite(frame_time)) throw std::invalid_argument("--fps must be a number > 0");
  if (!(dt >= 0) || !std::isfinite(dt)) throw std::invalid_argument("--dt must be a time >= 0 (0 = automatic)");
  if (!(object_size > 0 && object_size <= 0.8))
    throw std::invalid_argument("--object-size must lie in (0, 0.8] (box units; the box is 1 across)");
  if (!(min_opacity >= 0 && min_opacity < 1)) throw std::invalid_argument("--min-opacity must lie in [0, 1)");
  if (!(friction >= 0) || !std::isfinite(friction)) throw std::invalid_argument("--friction must be a number >= 0");
  if (!(damping >= 0) || !std::isfinite(damping))
    throw std::invalid_argument("--damping must be a rate >= 0 per second (0 = none)");
  if (up && !(up->norm() > 0 && up->allFinite())) throw std::invalid_argument("--up must be a nonzero vector");
  if (gravity && !gravity->allFinite()) throw std::invalid_argument("--gravity must be finite");
  if (!force.allFinite()) throw std::invalid_argument("--force must be finite");
}

double ground_below(const std::vector<Eigen::Vector3d>& points, const std::vector<Eigen::Vector3d>& object,
                    const Eigen::Vector3d& up) {
  if (object.empty()) throw std::invalid_argument("ground_below: no object points");
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  std::vector<double> heights;
  for (const Eigen::Vector3d& p : object) {
    centre += p;
    heights.push_back(p.dot(up));
  }
  centre /= static_cast<double>(object.size());
  auto across = [&](const Eigen::Vector3d& p) {
    const Eigen::Vector3d d = p - centre;
    return (d - d.dot(up) * up).norm();
  };
  std::vector<double> radii;
  for (const Eigen::Vector3d& p : object) radii.push_back(across(p));
  const double radius = quantile(radii, 0.9);
  const double low = quantile(heights, 0.1);
  // Widen the search when few points lie close under the object.
  for (double reach : {1.5, 3.0, 6.0}) {
    std::vector<double> below;
    for (const Eigen::Vector3d& p : points)
      if (p.dot(up) < low && across(p) < reach * radius) below.push_back(p.dot(up));
    if (below.size() >= 10) return quantile(below, 0.9);
  }
  return *std::min_element(heights.begin(), heights.end());
}

double support_height(const std::vector<Eigen::Vector3d>& points, const std::vector<Eigen::Vector3d>& object,
                      const Eigen::Vector3d& up, const std::optional<Plane>& floor) {
  if (floor && !object.empty()) {
    std::vector<double> heights;
    for (const Eigen::Vector3d& p : object) heights.push_back(p.dot(up));
    const double lo = quantile(heights, 0.02), hi = quantile(heights, 0.98);
    const double plane = floor->offset * floor->normal.dot(up);  // the plane's height along up
    if (std::abs(lo - plane) <= kOnFloor * (hi - lo)) return plane;
  }
  return ground_below(points, object, up);
}

std::vector<Eigen::Vector3d> fill_solid(const std::vector<Eigen::Vector3d>& surface, double cell) {
  const int n = std::max(1, static_cast<int>(std::ceil(1.0 / cell)));
  // The occupied cells of the grid over [0, 1]^3, in the box around them
  // grown by 2 cells (everything below happens within a cell of them).
  std::vector<std::array<int, 3>> cells;
  std::array<int, 3> lo = {n, n, n}, hi = {-1, -1, -1};
  for (const Eigen::Vector3d& p : surface) {
    std::array<int, 3> c;
    bool inside = true;
    for (int a = 0; a < 3; ++a) {
      c[a] = static_cast<int>(std::floor(p(a) / cell));
      inside = inside && c[a] >= 0 && c[a] < n;
    }
    if (!inside) continue;
    cells.push_back(c);
    for (int a = 0; a < 3; ++a) {
      lo[a] = std::min(lo[a], c[a]);
      hi[a] = std::max(hi[a], c[a]);
    }
  }
  if (cells.empty()) return {};
  std::array<int, 3> d;
  for (int a = 0; a < 3; ++a) {
    lo[a] = std::max(lo[a] - 2, 0);
    hi[a] = std::min(hi[a] + 2, n - 1);
    d[a] = hi[a] - lo[a] + 1;
  }
  auto id = [&d](int i, int j, int k) { return (static_cast<size_t>(i) * d[1] + j) * d[2] + k; };
  std::vector<uint8_t> occ(static_cast<size_t>(d[0]) * d[1] * d[2], 0);
  for (const auto& c : cells) occ[id(c[0] - lo[0], c[1] - lo[1], c[2] - lo[2])] = 1;
  // Grow or shrink a cell set by one cell (26 neighbours).
  auto morph = [&](const std::vector<uint8_t>& in, bool grow) {
    std::vector<uint8_t> out(in.size(), 0);
    for (int i = 0; i < d[0]; ++i)
      for (int j = 0; j < d[1]; ++j)
        for (int k = 0; k < d[2]; ++k) {
          bool any = false, all = true;
          for (int a = -1; a <= 1; ++a)
            for (int b = -1; b <= 1; ++b)
              for (int c = -1; c <= 1; ++c) {
                const int x = i + a, y = j + b, z = k + c;
                const bool v = x >= 0 && y >= 0 && z >= 0 && x < d[0] && y < d[1] && z < d[2] && in[id(x, y, z)];
                any = any || v;
                all = all && v;
              }
          out[id(i, j, k)] = grow ? any : all;
        }
    return out;
  };
  // Close gaps of a cell between the Gaussians (they may lie sparser than
  // the grid), then find the cells the closed shell encloses: seen[a][dir],
  // a shell cell lies before (dir 0) / after (dir 1) this cell along axis a.
  const std::vector<uint8_t> shell = morph(occ, true);
  std::vector<uint8_t> seen[3][2];
  for (int a = 0; a < 3; ++a)
    for (int dir = 0; dir < 2; ++dir) {
      std::vector<uint8_t>& s = seen[a][dir];
      s.assign(shell.size(), 0);
      const int du = d[(a + 1) % 3], dv = d[(a + 2) % 3], dw = d[a];
      for (int u = 0; u < du; ++u)
        for (int v = 0; v < dv; ++v) {
          uint8_t any = 0;
          for (int w0 = 0; w0 < dw; ++w0) {
            const int w = dir == 0 ? w0 : dw - 1 - w0;
            int c[3];
            c[a] = w;
            c[(a + 1) % 3] = u;
            c[(a + 2) % 3] = v;
            const size_t i = id(c[0], c[1], c[2]);
            s[i] = any;
            any = any | shell[i];
          }
        }
    }
  std::vector<uint8_t> solid = shell;
  for (size_t c = 0; c < solid.size(); ++c) {
    bool enclosed = true;
    for (int a = 0; a < 3 && enclosed; ++a) enclosed = seen[a][0][c] && seen[a][1][c];
    solid[c] = solid[c] || enclosed;
  }
  // Shrink back by the cell the closing added, keeping every occupied cell.
  const std::vector<uint8_t> core = morph(solid, false);
  std::vector<Eigen::Vector3d> out;
  for (int i = 0; i < d[0]; ++i)
    for (int j = 0; j < d[1]; ++j)
      for (int k = 0; k < d[2]; ++k)
        if (core[id(i, j, k)] || occ[id(i, j, k)])
          out.emplace_back((lo[0] + i + 0.5) * cell, (lo[1] + j + 0.5) * cell, (lo[2] + k + 0.5) * cell);
  return out;
}

Simulation::Simulation(Runtime& rt, const GaussianSet& scene, const std::vector<uint8_t>& selected,
                       const std::vector<Camera>& cameras, const std::vector<Eigen::Vector3d>& points,
                       const SimulationSettings& settings)
    : rt_(rt),
      settings_(settings),
      scene_(scene),
      d_particle_(&rt),
      d_scales0_(&rt),
      d_quats0_(&rt),
      d_sh0_(&rt),
      d_frame_(&rt),
      d_means_(&rt),
      d_scales_(&rt),
      d_quats_(&rt),
      d_sh_(&rt) {
  settings_.validate();
  if (selected.size() != scene.size()) throw std::invalid_argument("simulation: one selection flag per Gaussian");
  auto position = [&](size_t g) {
    return Eigen::Vector3d(scene.means[3 * g], scene.means[3 * g + 1], scene.means[3 * g + 2]);
  };
  std::vector<Eigen::Vector3d> object;
  for (size_t g = 0; g < scene.size(); ++g)
    if (selected[g] && scene.opacities[g] > settings_.min_opacity) object.push_back(position(g));
  if (object.empty())
    throw std::runtime_error("the selection has no Gaussian above opacity " + std::to_string(settings_.min_opacity) +
                             ": nothing to simulate (try another click or phrase)");

  place_box(object, cameras, points);
  start_solver(add_particles(selected));
  upload_gaussians();
}

void Simulation::place_box(const std::vector<Eigen::Vector3d>& object, const std::vector<Camera>& cameras,
                           const std::vector<Eigen::Vector3d>& points) {
  // ---- the box: up to +z, the object centred across, the ground (or the
  // object's base, when lower) at z = 0.15
  std::optional<Plane> floor;
  if (settings_.up) {
    frame_.up = settings_.up->normalized();
  } else {
    const SceneUp su = scene_up(cameras, points);
    frame_.up = su.up;
    if (su.from_plane) floor = su.plane;
  }
  Eigen::Vector3d e1 = frame_.up.unitOrthogonal();
  if (!cameras.empty()) {  // across-axis x along the first camera's right, when it is not vertical
    const Eigen::Vector3d right = cameras[0].R.row(0).transpose();
    const Eigen::Vector3d r = right - right.dot(frame_.up) * frame_.up;
    if (r.norm() > 1e-3) e1 = r.normalized();
  }
  frame_.A.row(0) = e1.transpose();
  frame_.A.row(1) = frame_.up.cross(e1).transpose();
  frame_.A.row(2) = frame_.up.transpose();
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(INFINITY), hi = -lo;
  for (const Eigen::Vector3d& p : object) {
    lo = lo.cwiseMin(frame_.A * p);
    hi = hi.cwiseMax(frame_.A * p);
  }
  frame_.ground_world = settings_.ground ? *settings_.ground : support_height(points, object, frame_.up, floor);
  // Inside the walls (3 cells) with 2 cells to spare: the object's largest
  // side is --object-size unless its height above the ground or its width
  // would not fit.
  const double dxg = 1.0 / settings_.grid, inner_lo = 5 * dxg, inner_hi = 1 - 5 * dxg;
  const double base = std::min(frame_.ground_world, lo(2));
  const double side = std::max({hi(0) - lo(0), hi(1) - lo(1), hi(2) - lo(2), 1e-9});
  const double floor_box = std::max(0.15, inner_lo);
  frame_.scale = std::min({settings_.object_size / side, (inner_hi - inner_lo) / std::max(hi(0) - lo(0), 1e-9),
                           (inner_hi - inner_lo) / std::max(hi(1) - lo(1), 1e-9),
                           (inner_hi - floor_box) / std::max(hi(2) - base, 1e-9)});
  frame_.origin = frame_.A.transpose() * Eigen::Vector3d(0.5 * (lo(0) + hi(0)), 0.5 * (lo(1) + hi(1)), base);
  frame_.box = Eigen::Vector3d(0.5, 0.5, floor_box);
  frame_.ground_box = frame_.to_box(frame_.A.transpose() * Eigen::Vector3d(0, 0, frame_.ground_world))(2);
  frame_.ground_box = std::clamp(frame_.ground_box, 0.0, 0.95);
}

std::vector<MpmMaterial> Simulation::add_particles(const std::vector<uint8_t>& selected) {
  const GaussianSet& scene = scene_;
  auto position = [&](size_t i) {
    return Eigen::Vector3d(scene.means[3 * i], scene.means[3 * i + 1], scene.means[3 * i + 2]);
  };
  // ---- particles: the object's Gaussians, its filled interior, the background
  const int g = settings_.grid;
  const double dx = 1.0 / g, lo_box = 3.0 * dx + 1e-6, hi_box = 1 - 3.0 * dx - 1e-6;
  auto inside = [&](const Eigen::Vector3d& x) { return (x.array() > lo_box).all() && (x.array() < hi_box).all(); };
  std::vector<Eigen::Vector3d> xs;
  std::vector<int32_t> mats;
  std::vector<Eigen::Vector3d> object_box;
  for (size_t i = 0; i < scene.size(); ++i) {
    if (!(scene.opacities[i] > settings_.min_opacity)) continue;
    const Eigen::Vector3d x = frame_.to_box(position(i));
    if (!inside(x)) continue;
    if (!selected[i] && !settings_.with_background) continue;
    // The support itself (background Gaussians within a cell of the ground
    // or below it) stays: the ground plane stands in for it. As particles,
    // a floor of soft background material tears under whatever slides on it.
    if (!selected[i] && x(2) < frame_.ground_box + dx) {
      ++support_gaussians_;
      continue;
    }
    moving_.push_back(static_cast<int32_t>(i));
    particle_.push_back(static_cast<int32_t>(xs.size()));
    xs.push_back(x);
    mats.push_back(selected[i] ? 0 : 1);
    if (selected[i]) {
      ++object_gaussians_;
      object_box.push_back(x);
    } else {
      ++background_gaussians_;
    }
  }
  if (object_gaussians_ == 0) throw std::runtime_error("the object does not fit the simulation box");
  // Two particles per cell and axis in every cell of the closed solid, so
  // that the object holds together where its Gaussians lie sparser than
  // the grid.
  for (const Eigen::Vector3d& c : fill_solid(object_box, dx))
    for (int s = 0; s < 8; ++s) {
      const Eigen::Vector3d x = c + 0.25 * dx * Eigen::Vector3d(s & 1 ? 1 : -1, s & 2 ? 1 : -1, s & 4 ? 1 : -1);
      if (!inside(x)) continue;
      xs.push_back(x);
      mats.push_back(0);
      ++fill_particles_;
    }
  // Each cell's volume, dx^3, shared by the particles in it.
  std::map<int64_t, int> per_cell;
  auto cell_of = [&](const Eigen::Vector3d& x) {
    const int64_t i = static_cast<int64_t>(x(0) * g), j = static_cast<int64_t>(x(1) * g),
                  k = static_cast<int64_t>(x(2) * g);
    return (i * g + j) * g + k;
  };
  for (const Eigen::Vector3d& x : xs) ++per_cell[cell_of(x)];
  // The background material only when it has particles: its stiffness
  // would otherwise shorten the substep for nothing.
  std::vector<MpmMaterial> materials = {settings_.object};
  if (settings_.with_background) materials.push_back(settings_.background);
  for (size_t p = 0; p < xs.size(); ++p) {
    const float vol = static_cast<float>(dx * dx * dx / per_cell[cell_of(xs[p])]);
    particles_.add({static_cast<float>(xs[p](0)), static_cast<float>(xs[p](1)), static_cast<float>(xs[p](2))}, vol,
                   mats[p], materials[mats[p]].density);
  }
  return materials;
}

void Simulation::start_solver(const std::vector<MpmMaterial>& materials) {
  const int g = settings_.grid;
  MpmConfig config;
  config.grid = g;
  config.ground = frame_.ground_box;
  config.friction = settings_.friction;
  config.damping = settings_.damping;
  const Eigen::Vector3d gravity =
      settings_.gravity ? Eigen::Vector3d(frame_.A * *settings_.gravity) : Eigen::Vector3d(0, 0, -9.8);
  config.gravity = {gravity(0), gravity(1), gravity(2)};
  std::vector<MpmMaterial> mm = materials;
  const Eigen::Vector3d force = frame_.A * settings_.force;
  mm[0].force = {force(0), force(1), force(2)};
  solver_ = std::make_unique<MpmSolver>(rt_, config, mm);
  solver_->upload(particles_);
  if (settings_.dt > 0 && settings_.dt > solver_->max_stable_dt(0)) {
    char buf[256];
    std::snprintf(buf, sizeof buf,
                  "--dt %.3g s is above the largest stable substep, %.3g s, for E = %.3g Pa at grid %d (the elastic "
                  "wave would cross a cell in one substep): use --dt %.3g or leave --dt out",
                  settings_.dt, solver_->max_stable_dt(0),
                  settings_.with_background ? std::max(settings_.object.E, settings_.background.E) : settings_.object.E,
                  g, solver_->max_stable_dt(0));
    throw std::invalid_argument(buf);
  }
  // The speed gravity and the force can add within one frame.
  speed_gain_ = (gravity.norm() + force.norm()) * settings_.frame_time;
  max_speed_ = speed_gain_;
}

void Simulation::upload_gaussians() {
  // The trained Gaussians of the particles, for mpm_gaussians.
  const size_t m = moving_.size();
  const int K = scene_.sh_coeffs();
  std::vector<float> s0(3 * m), q0(4 * m), sh0(static_cast<size_t>(3) * K * m);
  for (size_t i = 0; i < m; ++i) {
    const size_t gi = moving_[i];
    for (int c = 0; c < 3; ++c) s0[3 * i + c] = scene_.scales[3 * gi + c];
    for (int c = 0; c < 4; ++c) q0[4 * i + c] = scene_.quats[4 * gi + c];
    for (int c = 0; c < 3 * K; ++c) sh0[3 * K * i + c] = scene_.sh[3 * K * gi + c];
  }
  d_particle_.upload(particle_);
  d_scales0_.upload(s0);
  d_quats0_.upload(q0);
  d_sh0_.upload(sh0);
  std::vector<float> fr(16);
  for (int i = 0; i < 9; ++i) fr[i] = static_cast<float>(frame_.A(i / 3, i % 3));
  fr[9] = static_cast<float>(frame_.scale);
  for (int i = 0; i < 3; ++i) {
    fr[10 + i] = static_cast<float>(frame_.origin(i));
    fr[13 + i] = static_cast<float>(frame_.box(i));
  }
  d_frame_.upload(fr);
}

SimFrameStats Simulation::stats() const {
  SimFrameStats s;
  const double dx = 1.0 / settings_.grid;
  s.frame = frames_done_;
  s.time = frames_done_ * settings_.frame_time;
  s.all = diagnose(particles_, dx);
  s.object = diagnose(particles_, dx, 0);
  const auto c = centre_of_mass(particles_, 0);
  const Eigen::Vector3d w = frame_.to_world(Eigen::Vector3d(c[0], c[1], c[2]));
  s.object_centre = {w(0), w(1), w(2)};
  return s;
}

SimFrameStats Simulation::advance(bool forces_on) {
  const auto t0 = std::chrono::steady_clock::now();
  dt_ = settings_.dt > 0 ? settings_.dt : solver_->max_stable_dt(1.5 * max_speed_);
  const int substeps = std::max(1, static_cast<int>(std::ceil(settings_.frame_time / dt_ - 1e-9)));
  dt_ = settings_.frame_time / substeps;
  for (int s = 0; s < substeps; ++s) solver_->step(dt_, forces_on);
  solver_->download(particles_);
  ++frames_done_;
  SimFrameStats st = stats();
  st.substeps = substeps;
  st.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  if (!st.all.finite)
    throw std::runtime_error("the simulation became unstable in frame " + std::to_string(frames_done_) +
                             " (non-finite positions or strains): lower --dt, --E or --force, or raise --grid");
  double vmax = 0;
  for (size_t i = 0; i < particles_.size(); ++i)
    vmax = std::max(vmax, std::sqrt(static_cast<double>(particles_.v[3 * i]) * particles_.v[3 * i] +
                                    static_cast<double>(particles_.v[3 * i + 1]) * particles_.v[3 * i + 1] +
                                    static_cast<double>(particles_.v[3 * i + 2]) * particles_.v[3 * i + 2]));
  max_speed_ = vmax + speed_gain_;
  return st;
}

GaussianSet Simulation::gaussians(const Eigen::Vector3d& campos, bool bake) {
  GaussianSet out = scene_;
  const size_t m = moving_.size();
  if (m == 0) return out;
  const int K = scene_.sh_coeffs();
  const int K_active = K;
  d_means_.reserve(3 * m * sizeof(float));
  d_scales_.reserve(3 * m * sizeof(float));
  d_quats_.reserve(4 * m * sizeof(float));
  d_sh_.reserve(3 * m * K * sizeof(float));
  cl_float4 cp;
  for (int i = 0; i < 3; ++i) cp.s[i] = static_cast<float>(campos(i));
  cp.s[3] = 0.f;
  cl::Kernel k = rt_.kernel("mpm.cl", "mpm_gaussians", kNoDefines);
  set_kernel_args(k, static_cast<cl_int>(m), static_cast<cl_int>(K), static_cast<cl_int>(K_active), d_particle_,
                  solver_->positions(), solver_->deformation(), d_frame_, cp, d_scales0_, d_quats0_, d_sh0_, d_means_,
                  d_scales_, d_quats_, d_sh_);
  rt_.launch("mpm_gaussians", k, cl::NDRange((m + 63) / 64 * 64), cl::NDRange(64));
  std::vector<float> means, scales, quats, sh;
  d_means_.download(means, 3 * m);
  d_scales_.download(scales, 3 * m);
  d_quats_.download(quats, 4 * m);
  if (bake) d_sh_.download(sh, 3 * m * K);
  for (size_t i = 0; i < m; ++i) {
    const size_t gi = moving_[i];
    for (int c = 0; c < 3; ++c) {
      out.means[3 * gi + c] = means[3 * i + c];
      out.scales[3 * gi + c] = scales[3 * i + c];
    }
    for (int c = 0; c < 4; ++c) out.quats[4 * gi + c] = quats[4 * i + c];
    if (bake)
      for (int c = 0; c < 3 * K; ++c) out.sh[3 * K * gi + c] = sh[3 * K * i + c];
  }
  return out;
}

nlohmann::json Simulation::describe() const {
  auto material = [](const MpmMaterial& m) {
    return nlohmann::json{{"kind", material_name(m.kind)},
                          {"E", m.E},
                          {"nu", m.nu},
                          {"density", m.density},
                          {"yield_stress", m.yield_stress > 0 ? m.yield_stress : m.E / 100},
                          {"friction_deg", m.friction_deg},
                          {"softening", m.softening}};
  };
  auto vec = [](const Eigen::Vector3d& v) { return nlohmann::json::array({v(0), v(1), v(2)}); };
  const MpmConfig& c = solver_->config();
  return {{"materials", {{"object", material(settings_.object)}, {"background", material(settings_.background)}}},
          {"particles",
           {{"total", particles_.size()},
            {"object_gaussians", object_gaussians_},
            {"interior_fill", fill_particles_},
            {"background_gaussians",
             settings_.with_background ? nlohmann::json(background_gaussians_) : nlohmann::json(nullptr)}}},
          {"grid", settings_.grid},
          {"grid_nodes", static_cast<size_t>(settings_.grid) * settings_.grid * settings_.grid},
          {"frame_time", settings_.frame_time},
          {"gravity_box", {c.gravity[0], c.gravity[1], c.gravity[2]}},
          {"force_world", vec(settings_.force)},
          {"up", vec(frame_.up)},
          {"ground_world", frame_.ground_world},
          {"ground_box", frame_.ground_box},
          {"ground_friction", settings_.friction},
          {"damping", settings_.damping},
          {"box_scale", frame_.scale},
          {"object_size", settings_.object_size},
          {"min_opacity", settings_.min_opacity},
          {"max_stable_dt_at_rest", solver_->max_stable_dt(0)}};
}

}  // namespace ag2gs
