#include "host/physics/mpm.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <stdexcept>
#include <vector>

#include "host/device/kernel_call.h"

namespace ag2gs {

namespace {

const std::map<std::string, std::string> kNoDefines;
constexpr int kMatSize = 12;  // MAT_SIZE in kernels/mpm.cl
constexpr int kPdSize = 16;   // PD_SIZE
constexpr int kBound = 3;     // MPM_BOUND

cl_int4 int4_of(int a, int b, int c) {
  cl_int4 r;
  r.s[0] = a;
  r.s[1] = b;
  r.s[2] = c;
  r.s[3] = 0;
  return r;
}

size_t round_up(size_t n, size_t m) {
  return (n + m - 1) / m * m;
}

}  // namespace

MaterialKind parse_material(const std::string& name) {
  if (name == "jelly") return MaterialKind::kJelly;
  if (name == "metal") return MaterialKind::kMetal;
  if (name == "sand") return MaterialKind::kSand;
  if (name == "plasticine") return MaterialKind::kPlasticine;
  throw std::invalid_argument("unknown material '" + name + "': use jelly, metal, sand or plasticine");
}

const char* material_name(MaterialKind kind) {
  switch (kind) {
    case MaterialKind::kJelly:
      return "jelly";
    case MaterialKind::kMetal:
      return "metal";
    case MaterialKind::kSand:
      return "sand";
    case MaterialKind::kPlasticine:
      return "plasticine";
  }
  return "?";
}

double MpmMaterial::wave_speed() const {
  return std::sqrt((lambda() + 2 * mu()) / density);
}

void MpmParticles::add(const std::array<float, 3>& pos, float vol, int32_t m, double density) {
  x.insert(x.end(), pos.begin(), pos.end());
  v.insert(v.end(), {0.f, 0.f, 0.f});
  F.insert(F.end(), {1.f, 0.f, 0.f, 0.f, 1.f, 0.f, 0.f, 0.f, 1.f});
  C.insert(C.end(), 9, 0.f);
  volume.push_back(vol);
  mass.push_back(static_cast<float>(vol * density));
  plastic.push_back(0.f);
  material.push_back(m);
}

MpmDiagnostics diagnose(const MpmParticles& p, double dx, int of_material) {
  MpmDiagnostics d;
  for (size_t i = 0; i < p.size(); ++i) {
    for (int k = 0; k < 3; ++k) d.finite = d.finite && std::isfinite(p.x[3 * i + k]) && std::isfinite(p.v[3 * i + k]);
    for (int k = 0; k < 9; ++k) d.finite = d.finite && std::isfinite(p.F[9 * i + k]);
    if (of_material >= 0 && p.material[i] != of_material) continue;
    const double m = p.mass[i];
    const double x[3] = {p.x[3 * i], p.x[3 * i + 1], p.x[3 * i + 2]};
    const double v[3] = {p.v[3 * i], p.v[3 * i + 1], p.v[3 * i + 2]};
    d.kinetic += 0.5 * m * (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    for (int k = 0; k < 3; ++k) d.momentum[k] += m * v[k];
    d.angular[0] += m * (x[1] * v[2] - x[2] * v[1]);
    d.angular[1] += m * (x[2] * v[0] - x[0] * v[2]);
    d.angular[2] += m * (x[0] * v[1] - x[1] * v[0]);
    // APIC's particle spin: sum over the nodes of w (x_i - x_p) x C (x_i - x_p)
    // = eps_abc C_cb dx^2 / 4 for quadratic B-splines.
    const float* C = &p.C[9 * i];
    const double spin = m * dx * dx / 4;
    d.angular[0] += spin * (C[7] - C[5]);
    d.angular[1] += spin * (C[2] - C[6]);
    d.angular[2] += spin * (C[3] - C[1]);
    double s = 0;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) {
        const double e = p.F[9 * i + 3 * r + c] - (r == c ? 1.0 : 0.0);
        s += e * e;
      }
    d.max_strain = std::max(d.max_strain, std::sqrt(s));
  }
  return d;
}

std::array<double, 3> centre_of_mass(const MpmParticles& p, int of_material) {
  std::array<double, 3> c{};
  double m = 0;
  for (size_t i = 0; i < p.size(); ++i) {
    if (of_material >= 0 && p.material[i] != of_material) continue;
    for (int k = 0; k < 3; ++k) c[k] += static_cast<double>(p.mass[i]) * p.x[3 * i + k];
    m += p.mass[i];
  }
  if (m > 0)
    for (double& v : c) v /= m;
  return c;
}

PileShape measure_pile(const MpmParticles& p, double dx, double ground, double cx, double cy) {
  const int g = static_cast<int>(std::lround(1 / dx));
  std::vector<double> top(static_cast<size_t>(g) * g, -1);
  for (size_t i = 0; i < p.size(); ++i) {
    const int a = static_cast<int>(p.x[3 * i] / dx), b = static_cast<int>(p.x[3 * i + 1] / dx);
    if (a < 0 || b < 0 || a >= g || b >= g) continue;
    double& t = top[static_cast<size_t>(a) * g + b];
    t = std::max(t, p.x[3 * i + 2] - ground);
  }
  PileShape pile;
  pile.summit = std::max(0.0, *std::max_element(top.begin(), top.end()));
  double sr = 0, sz = 0, srr = 0, srz = 0;
  int n = 0;
  for (int a = 0; a < g; ++a)
    for (int b = 0; b < g; ++b) {
      const double z = top[static_cast<size_t>(a) * g + b];
      if (!(z > 0.2 * pile.summit && z < 0.8 * pile.summit)) continue;
      const double r = std::hypot((a + 0.5) * dx - cx, (b + 0.5) * dx - cy);
      sr += r;
      sz += z;
      srr += r * r;
      srz += r * z;
      ++n;
    }
  pile.flank_columns = n;
  pile.flank_deg = n >= 3 ? std::atan(-(n * srz - sr * sz) / (n * srr - sr * sr)) * 180 / M_PI
                          : std::numeric_limits<double>::quiet_NaN();
  return pile;
}

MpmSolver::MpmSolver(Runtime& rt, const MpmConfig& config, std::vector<MpmMaterial> materials)
    : rt_(rt),
      config_(config),
      materials_(std::move(materials)),
      x_(&rt),
      v_(&rt),
      F_(&rt),
      C_(&rt),
      volume_(&rt),
      mass_(&rt),
      plastic_(&rt),
      material_(&rt),
      mat_params_(&rt),
      keys_(&rt),
      order_(&rt),
      cell_start_(&rt),
      active_(&rt),
      pdata_(&rt),
      grid_v_(&rt) {
  if (config_.grid < 8 || config_.grid > 512)
    throw std::invalid_argument("simulation grid " + std::to_string(config_.grid) + " is outside 8..512 cells");
  if (!(config_.cfl > 0 && config_.cfl <= 1)) throw std::invalid_argument("the CFL number must be in (0, 1]");
  if (!(config_.friction >= 0) || !std::isfinite(config_.friction))
    throw std::invalid_argument("the ground's friction coefficient must be a finite number >= 0");
  if (!(config_.damping >= 0) || !std::isfinite(config_.damping))
    throw std::invalid_argument("the damping rate must be a finite number >= 0 (1/s)");
  if (materials_.empty()) throw std::invalid_argument("the simulation needs at least one material");
  std::vector<float> params;
  for (const MpmMaterial& m : materials_) {
    if (!(m.E > 0) || !std::isfinite(m.E))
      throw std::invalid_argument("Young's modulus E must be a finite number > 0 (got " + std::to_string(m.E) + ")");
    if (!(m.nu > -1 && m.nu < 0.5))
      throw std::invalid_argument("Poisson's ratio nu must be in (-1, 0.5) (got " + std::to_string(m.nu) + ")");
    if (!(m.density > 0) || !std::isfinite(m.density))
      throw std::invalid_argument("the density must be a finite number > 0 (got " + std::to_string(m.density) + ")");
    const double yield = m.yield_stress > 0 ? m.yield_stress : m.E / 100;
    const double sin_phi = std::sin(m.friction_deg * M_PI / 180);
    const double alpha = std::sqrt(2.0 / 3.0) * 2 * sin_phi / (3 - sin_phi);
    const float row[kMatSize] = {static_cast<float>(m.kind),
                                 static_cast<float>(m.mu()),
                                 static_cast<float>(m.lambda()),
                                 static_cast<float>(yield),
                                 static_cast<float>(alpha),
                                 static_cast<float>(m.softening),
                                 static_cast<float>(m.force[0]),
                                 static_cast<float>(m.force[1]),
                                 static_cast<float>(m.force[2]),
                                 0.f,
                                 0.f,
                                 0.f};
    params.insert(params.end(), row, row + kMatSize);
  }
  mat_params_.upload(params);
}

void MpmSolver::upload(const MpmParticles& p) {
  n_ = p.size();
  if (p.x.size() != 3 * n_ || p.v.size() != 3 * n_ || p.F.size() != 9 * n_ || p.C.size() != 9 * n_ ||
      p.volume.size() != n_ || p.plastic.size() != n_ || p.material.size() != n_)
    throw std::invalid_argument("simulation particles: the arrays disagree on the particle count");
  const double lo = kBound / static_cast<double>(config_.grid), hi = 1 - lo;
  for (size_t i = 0; i < n_; ++i) {
    for (int k = 0; k < 3; ++k)
      if (!(p.x[3 * i + k] >= lo && p.x[3 * i + k] <= hi))
        throw std::invalid_argument("simulation particle " + std::to_string(i) +
                                    " lies outside the box's inner part [" + std::to_string(lo) + ", " +
                                    std::to_string(hi) + "]^3");
    if (p.material[i] < 0 || static_cast<size_t>(p.material[i]) >= materials_.size())
      throw std::invalid_argument("simulation particle " + std::to_string(i) + " has material " +
                                  std::to_string(p.material[i]) + " of " + std::to_string(materials_.size()));
  }
  x_.upload(p.x);
  v_.upload(p.v);
  F_.upload(p.F);
  C_.upload(p.C);
  volume_.upload(p.volume);
  mass_.upload(p.mass);
  plastic_.upload(p.plastic);
  material_.upload(p.material);
  keys_.reserve(std::max<size_t>(n_, 1) * sizeof(int32_t));
  pdata_.reserve(std::max<size_t>(n_, 1) * kPdSize * sizeof(float));
}

void MpmSolver::download(MpmParticles& p) const {
  x_.download(p.x, 3 * n_);
  v_.download(p.v, 3 * n_);
  F_.download(p.F, 9 * n_);
  C_.download(p.C, 9 * n_);
  volume_.download(p.volume, n_);
  mass_.download(p.mass, n_);
  plastic_.download(p.plastic, n_);
  material_.download(p.material, n_);
}

double MpmSolver::max_stable_dt(double max_speed) const {
  double c = 0;
  for (const MpmMaterial& m : materials_) c = std::max(c, m.wave_speed());
  const double dx = 1.0 / config_.grid;
  return config_.cfl * dx / (c + std::max(max_speed, 0.0));
}

void MpmSolver::sort_by_cell() {
  const int g = config_.grid;
  cl::Kernel kk = rt_.kernel("mpm.cl", "mpm_keys", kNoDefines);
  KernelCall(kk)
      .arg("n", static_cast<cl_int>(n_))
      .arg("inv_dx", static_cast<float>(g))
      .arg("grid", static_cast<cl_int>(g))
      .buffer("x", x_, n_ * 3 * sizeof(float))
      .buffer("keys", keys_, n_ * sizeof(int32_t))
      .done();
  rt_.launch("mpm_keys", kk, cl::NDRange(round_up(n_, 64)), cl::NDRange(64));
  keys_.download(keys_host_, n_);
  // The cell box the particles occupy, then a stable counting sort over it.
  lo_ = {g, g, g};
  hi_ = {-1, -1, -1};
  for (int32_t key : keys_host_) {
    const int c[3] = {key / (g * g), (key / g) % g, key % g};
    for (int k = 0; k < 3; ++k) {
      lo_[k] = std::min(lo_[k], c[k]);
      hi_[k] = std::max(hi_[k], c[k]);
    }
  }
  const int d[3] = {hi_[0] - lo_[0] + 1, hi_[1] - lo_[1] + 1, hi_[2] - lo_[2] + 1};
  const size_t cells = static_cast<size_t>(d[0]) * d[1] * d[2];
  start_host_.assign(cells + 1, 0);
  auto local = [&](int32_t key) {
    const int c[3] = {key / (g * g) - lo_[0], (key / g) % g - lo_[1], key % g - lo_[2]};
    return (static_cast<size_t>(c[0]) * d[1] + c[1]) * d[2] + c[2];
  };
  for (int32_t key : keys_host_) ++start_host_[local(key) + 1];
  for (size_t c = 0; c < cells; ++c) start_host_[c + 1] += start_host_[c];
  order_host_.resize(n_);
  std::vector<int32_t> next(start_host_.begin(), start_host_.end() - 1);
  for (size_t i = 0; i < n_; ++i) order_host_[next[local(keys_host_[i])]++] = static_cast<int32_t>(i);
  order_.upload(order_host_);
  cell_start_.upload(start_host_);
  // The nodes some particle reaches: base cell + 0..2 on each axis, in
  // increasing id order, in the node box (the cell box grown by 2).
  const int nd[3] = {d[0] + 2, d[1] + 2, d[2] + 2};
  active_mark_.assign(static_cast<size_t>(nd[0]) * nd[1] * nd[2], 0);
  for (int i = 0; i < d[0]; ++i)
    for (int j = 0; j < d[1]; ++j)
      for (int k = 0; k < d[2]; ++k) {
        const size_t c = (static_cast<size_t>(i) * d[1] + j) * d[2] + k;
        if (start_host_[c + 1] == start_host_[c]) continue;
        for (int a = 0; a < 3; ++a)
          for (int b = 0; b < 3; ++b)
            for (int e = 0; e < 3; ++e)
              active_mark_[(static_cast<size_t>(i + a) * nd[1] + (j + b)) * nd[2] + (k + e)] = 1;
      }
  active_host_.clear();
  for (size_t id = 0; id < active_mark_.size(); ++id)
    if (active_mark_[id]) active_host_.push_back(static_cast<int32_t>(id));
  active_.upload(active_host_);
}

void MpmSolver::step(double dt, bool forces_on) {
  if (n_ == 0) return;
  if (!(dt > 0) || !std::isfinite(dt)) throw std::invalid_argument("the substep must be a finite time > 0");
  const int g = config_.grid;
  const float dx = 1.f / g, inv_dx = static_cast<float>(g);
  sort_by_cell();
  const int wg = 64;

  const size_t f4 = sizeof(float), i4 = sizeof(int32_t);
  cl::Kernel ks = rt_.kernel("mpm.cl", "mpm_particle_stress", kNoDefines);
  KernelCall(ks)
      .arg("n", static_cast<cl_int>(n_))
      .arg("dt", static_cast<float>(dt))
      .arg("inv_dx", inv_dx)
      .arg("forces_on", static_cast<cl_int>(forces_on))
      .buffer("order", order_, n_ * i4)
      .buffer("x", x_, n_ * 3 * f4)
      .buffer("v", v_, n_ * 3 * f4)
      .buffer("F", F_, n_ * 9 * f4)
      .buffer("C", C_, n_ * 9 * f4)
      .buffer("volume", volume_, n_ * f4)
      .buffer("mass", mass_, n_ * f4)
      .buffer("plastic", plastic_, n_ * f4)
      .buffer("material", material_, n_ * i4)
      .buffer("mat_params", mat_params_, materials_.size() * kMatSize * f4)
      .buffer("pdata", pdata_, n_ * kPdSize * f4)
      .done();
  rt_.launch("mpm_particle_stress", ks, cl::NDRange(round_up(n_, wg)), cl::NDRange(wg));

  // Nodes the particles reach: their base cells plus 2 on each axis.
  const cl_int4 clo = int4_of(lo_[0], lo_[1], lo_[2]);
  const cl_int4 cdim = int4_of(hi_[0] - lo_[0] + 1, hi_[1] - lo_[1] + 1, hi_[2] - lo_[2] + 1);
  const cl_int4 ndim = int4_of(cdim.s[0] + 2, cdim.s[1] + 2, cdim.s[2] + 2);
  const size_t nodes = static_cast<size_t>(ndim.s[0]) * ndim.s[1] * ndim.s[2];
  grid_v_.reserve(nodes * 4 * sizeof(float));
  cl_float4 gravity;
  for (int k = 0; k < 3; ++k) gravity.s[k] = static_cast<float>(config_.gravity[k]);
  gravity.s[3] = 0.f;
  cl::Kernel kg = rt_.kernel("mpm.cl", "mpm_grid", kNoDefines);
  const size_t n_active = active_host_.size();
  // The grid size, the substep and the node box (its low corner is the cell
  // box's), as both grid kernels take them after their count.
  auto grid_args = [&](KernelCall& call) -> KernelCall& {
    return call.arg("grid", static_cast<cl_int>(g))
        .arg("dt", static_cast<float>(dt))
        .arg("dx", dx)
        .arg("inv_dx", inv_dx)
        .arg("nlo", clo)
        .arg("ndim", ndim);
  };
  grid_args(KernelCall(kg).arg("n_active", static_cast<cl_int>(n_active)))
      .arg("clo", clo)
      .arg("cdim", cdim)
      .arg("gravity", gravity)
      .arg("ground", static_cast<float>(config_.ground))
      .arg("friction", static_cast<float>(config_.friction))
      .arg("keep_speed", static_cast<float>(1.0 / (1.0 + config_.damping * dt)))
      .buffer("active", active_, n_active * i4)
      .buffer("cell_start", cell_start_, start_host_.size() * i4)
      .buffer("pdata", pdata_, n_ * kPdSize * f4)
      .buffer("grid_v", grid_v_, nodes * 4 * f4)
      .done();
  rt_.launch("mpm_grid", kg, cl::NDRange(round_up(n_active, wg)), cl::NDRange(wg));

  cl::Kernel kp = rt_.kernel("mpm.cl", "mpm_g2p", kNoDefines);
  grid_args(KernelCall(kp).arg("n", static_cast<cl_int>(n_)))
      .buffer("grid_v", grid_v_, nodes * 4 * f4)
      .buffer("x", x_, n_ * 3 * f4)
      .buffer("v", v_, n_ * 3 * f4)
      .buffer("F", F_, n_ * 9 * f4)
      .buffer("C", C_, n_ * 9 * f4)
      .done();
  rt_.launch("mpm_g2p", kp, cl::NDRange(round_up(n_, wg)), cl::NDRange(wg));
}

}  // namespace ag2gs
