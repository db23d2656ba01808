#include "train/graph/anchor_graph.h"

#include <algorithm>
#include <cstdio>
#include <limits>
#include <stdexcept>

#include "host/io/json_input.h"

namespace ag2gs {

namespace {

constexpr int kMaxCellScale = 1024;
constexpr int kCellKeyBits = 21;  // per axis; cells are within +-2^19, neighbours +-1 more
constexpr int64_t kCellKeyBias = int64_t(1) << 20;

int64_t floor_div(int64_t a, int64_t b) {
  int64_t q = a / b;
  if (a % b != 0 && a < 0) --q;
  return q;
}

uint64_t cell_key(int64_t x, int64_t y, int64_t z) {
  return (static_cast<uint64_t>(x + kCellKeyBias) << (2 * kCellKeyBits)) |
         (static_cast<uint64_t>(y + kCellKeyBias) << kCellKeyBits) | static_cast<uint64_t>(z + kCellKeyBias);
}

// Open-addressing hash (linear probing, power-of-two capacity) from cell key
// to a dense cell index. Only lookups by key: its slot order never matters.
class CellTable {
 public:
  explicit CellTable(size_t expected) {
    size_t cap = 16;
    while (cap < 2 * expected + 1) cap <<= 1;
    keys_.assign(cap, kEmpty);
    values_.assign(cap, -1);
    mask_ = cap - 1;
  }
  // The index of `key`, inserting `next` when absent; sets `inserted`.
  int32_t find_or_insert(uint64_t key, int32_t next, bool& inserted) {
    for (size_t s = hash(key) & mask_;; s = (s + 1) & mask_) {
      if (keys_[s] == key) {
        inserted = false;
        return values_[s];
      }
      if (keys_[s] == kEmpty) {
        keys_[s] = key;
        values_[s] = next;
        inserted = true;
        return next;
      }
    }
  }
  int32_t find(uint64_t key) const {
    for (size_t s = hash(key) & mask_;; s = (s + 1) & mask_) {
      if (keys_[s] == key) return values_[s];
      if (keys_[s] == kEmpty) return -1;
    }
  }

 private:
  static constexpr uint64_t kEmpty = ~uint64_t(0);  // never a cell key (the top bit is unused)
  static size_t hash(uint64_t k) {                  // splitmix64 finaliser
    k ^= k >> 30;
    k *= 0xbf58476d1ce4e5b9ull;
    k ^= k >> 27;
    k *= 0x94d049bb133111ebull;
    k ^= k >> 31;
    return static_cast<size_t>(k);
  }
  std::vector<uint64_t> keys_;
  std::vector<int32_t> values_;
  size_t mask_ = 0;
};

[[noreturn]] void fail_archive(const ModelArchive& archive, const std::string& what) {
  throw std::runtime_error((archive.source.empty() ? std::string("model") : archive.source) +
                           ": anchor graph: " + what);
}

std::string hex64(uint64_t v) {
  char buf[20];
  std::snprintf(buf, sizeof buf, "%016llx", static_cast<unsigned long long>(v));
  return buf;
}

}  // namespace

uint64_t AnchorGraph::anchor_fingerprint(const AnchorModel& model) {
  const int64_t head[2] = {model.grid().layer_ratio, static_cast<int64_t>(model.size())};
  uint64_t h = fnv1a64(head, sizeof head);
  h = fnv1a64(model.layer().data(), model.layer().size() * sizeof(int32_t), h);
  return fnv1a64(model.cell().data(), model.cell().size() * sizeof(int32_t), h);
}

bool AnchorGraph::matches(const AnchorModel& model) const {
  return anchors() == model.size() && fingerprint_ == anchor_fingerprint(model);
}

AnchorGraph AnchorGraph::build(const AnchorModel& model, int cell_scale) {
  if (cell_scale < 1 || cell_scale > kMaxCellScale)
    throw std::invalid_argument("anchor graph: cell_scale " + std::to_string(cell_scale) + " must lie in 1.." +
                                std::to_string(kMaxCellScale) + " (1 = the top-layer voxel)");
  model.check();
  const size_t A = model.size();
  if (A > static_cast<size_t>(std::numeric_limits<int32_t>::max()))
    throw std::invalid_argument("anchor graph: " + std::to_string(A) + " anchors exceed the 32-bit anchor ids");
  AnchorGraph g;
  g.cell_scale_ = cell_scale;
  g.fingerprint_ = anchor_fingerprint(model);
  g.row_offsets_.assign(A + 1, 0);
  if (A == 0) return g;

  // 1. Neighbourhood cell of every anchor; dense cell ids in order of first
  //    appearance (deterministic: anchor order is fixed).
  const VoxelGrid& grid = model.grid();
  const std::vector<int32_t>& layer = model.layer();
  const std::vector<int32_t>& cell = model.cell();
  std::vector<int64_t> ratio_pow(grid.layers, 1);
  for (int l = 1; l < grid.layers; ++l) ratio_pow[l] = ratio_pow[l - 1] * grid.layer_ratio;
  CellTable table(A);
  std::vector<int32_t> cell_of(A);
  std::vector<int64_t> cell_xyz;  // [cells,3]
  int32_t cells = 0;
  for (size_t i = 0; i < A; ++i) {
    const int64_t f = ratio_pow.at(layer[i]) * cell_scale;  // anchor cells per neighbourhood cell, per axis
    const int64_t x = floor_div(cell[3 * i], f), y = floor_div(cell[3 * i + 1], f), z = floor_div(cell[3 * i + 2], f);
    bool inserted = false;
    cell_of[i] = table.find_or_insert(cell_key(x, y, z), cells, inserted);
    if (inserted) {
      cell_xyz.insert(cell_xyz.end(), {x, y, z});
      ++cells;
    }
  }
  // Members of each cell, ascending anchor ids (counting sort by cell).
  std::vector<int32_t> member_off(cells + 1, 0), members(A);
  for (size_t i = 0; i < A; ++i) ++member_off[cell_of[i] + 1];
  for (int32_t c = 0; c < cells; ++c) member_off[c + 1] += member_off[c];
  {
    std::vector<int32_t> fill(member_off.begin(), member_off.end() - 1);
    for (size_t i = 0; i < A; ++i) members[fill[cell_of[i]]++] = static_cast<int32_t>(i);
  }

  // 2. The (up to 27) occupied cells around each cell, and row lengths:
  //    every member of cell c has the same neighbourhood, minus itself.
  std::vector<int32_t> near_off(cells + 1, 0), near;
  near.reserve(static_cast<size_t>(cells) * 9);
  std::vector<int64_t> hood_size(cells, 0);
  for (int32_t c = 0; c < cells; ++c) {
    const int64_t* p = &cell_xyz[3 * static_cast<size_t>(c)];
    for (int dx = -1; dx <= 1; ++dx)
      for (int dy = -1; dy <= 1; ++dy)
        for (int dz = -1; dz <= 1; ++dz) {
          const int32_t n = table.find(cell_key(p[0] + dx, p[1] + dy, p[2] + dz));
          if (n < 0) continue;
          near.push_back(n);
          hood_size[c] += member_off[n + 1] - member_off[n];
        }
    near_off[c + 1] = static_cast<int32_t>(near.size());
  }
  int64_t total = 0;
  for (size_t i = 0; i < A; ++i) {
    total += hood_size[cell_of[i]] - 1;
    if (total > std::numeric_limits<int32_t>::max())
      throw std::invalid_argument("anchor graph: more than 2^31 neighbour entries (" + std::to_string(A) +
                                  " anchors, cell_scale " + std::to_string(cell_scale) +
                                  "); use a smaller cell_scale or fewer anchors");
    g.row_offsets_[i + 1] = static_cast<int32_t>(total);
  }

  // 3. Per cell: merge the neighbouring cells' member lists once (sorted
  //    ascending), then write it, minus the anchor itself, as each member's row.
  g.neighbours_.resize(static_cast<size_t>(total));
  std::vector<int32_t> hood;
  for (int32_t c = 0; c < cells; ++c) {
    hood.clear();
    for (int32_t k = near_off[c]; k < near_off[c + 1]; ++k) {
      const int32_t n = near[k];
      hood.insert(hood.end(), members.begin() + member_off[n], members.begin() + member_off[n + 1]);
    }
    std::sort(hood.begin(), hood.end());
    for (int32_t m = member_off[c]; m < member_off[c + 1]; ++m) {
      const int32_t i = members[m];
      int32_t* out = g.neighbours_.data() + g.row_offsets_[i];
      for (int32_t j : hood)
        if (j != i) *out++ = j;
    }
  }
  return g;
}

std::vector<int64_t> AnchorGraph::degree_histogram() const {
  std::vector<int64_t> hist;
  for (size_t i = 0; i < anchors(); ++i) {
    const int d = degree(i);
    size_t bin = 0;
    while (bin < 32 && (int64_t(1) << bin) <= d) ++bin;  // bin b >= 1 holds [2^(b-1), 2^b)
    if (hist.size() <= bin) hist.resize(bin + 1, 0);
    ++hist[bin];
  }
  return hist;
}

void AnchorGraph::validate(const std::string& who) const {
  auto fail = [&](const std::string& what) { throw std::logic_error(who + ": " + what); };
  if (row_offsets_.empty() || row_offsets_[0] != 0) fail("row_offsets must start with 0");
  if (static_cast<size_t>(row_offsets_.back()) != neighbours_.size())
    fail("row_offsets ends at " + std::to_string(row_offsets_.back()) + " but there are " +
         std::to_string(neighbours_.size()) + " neighbour entries");
  const int64_t A = static_cast<int64_t>(anchors());
  for (int64_t i = 0; i < A; ++i) {
    if (row_offsets_[i + 1] < row_offsets_[i]) fail("row_offsets decreases at row " + std::to_string(i));
    for (int32_t k = row_offsets_[i]; k < row_offsets_[i + 1]; ++k) {
      const int32_t j = neighbours_[k];
      if (j < 0 || j >= A)
        fail("row " + std::to_string(i) + " names anchor " + std::to_string(j) + ", outside 0.." +
             std::to_string(A - 1));
      if (j == i) fail("row " + std::to_string(i) + " has a self loop");
      if (k > row_offsets_[i] && neighbours_[k - 1] >= j)
        fail("row " + std::to_string(i) + " is not strictly ascending (duplicate or unsorted neighbour)");
    }
  }
  for (int64_t i = 0; i < A; ++i)
    for (int32_t k = row_offsets_[i]; k < row_offsets_[i + 1]; ++k) {
      const int32_t j = neighbours_[k];
      if (!std::binary_search(neighbours_.begin() + row_offsets_[j], neighbours_.begin() + row_offsets_[j + 1],
                              static_cast<int32_t>(i)))
        fail("not symmetric: " + std::to_string(j) + " is in row " + std::to_string(i) + " but " + std::to_string(i) +
             " is not in row " + std::to_string(j));
    }
}

void AnchorGraph::to_archive(ModelArchive& archive) const {
  const int64_t A = static_cast<int64_t>(anchors()), E = static_cast<int64_t>(entries());
  archive.put("graph/row_offsets", row_offsets_, {A + 1});
  archive.put("graph/neighbours", neighbours_, {E});
  archive.meta["graph"] = {{"format", 1},
                           {"cell_scale", cell_scale_},
                           {"anchors", A},
                           {"entries", E},
                           {"anchor_fingerprint", hex64(fingerprint_)}};
}

AnchorGraph AnchorGraph::from_archive(const ModelArchive& archive) {
  if (!in_archive(archive)) fail_archive(archive, "the archive has no meta entry 'graph' (no graph was saved)");
  AnchorGraph g;
  int64_t A = 0, E = 0;
  try {
    const nlohmann::json& m = archive.meta.at("graph");
    if (m.at("format").get<int>() != 1)
      fail_archive(archive, "meta 'graph' has format " + m.at("format").dump() + "; this build reads format 1");
    g.cell_scale_ = m.at("cell_scale").get<int>();
    A = m.at("anchors").get<int64_t>();
    E = m.at("entries").get<int64_t>();
    const std::string fp = m.at("anchor_fingerprint").get<std::string>();
    size_t used = 0;
    g.fingerprint_ = std::stoull(fp, &used, 16);
    if (used != fp.size()) throw std::invalid_argument("fingerprint");
  } catch (const nlohmann::json::exception& e) {
    fail_archive(archive, std::string("meta 'graph' is incomplete or mistyped: ") + json_error_text(e));
  } catch (const std::logic_error&) {  // stoull
    fail_archive(archive, "meta 'graph': anchor_fingerprint is not a hexadecimal number");
  }
  if (g.cell_scale_ < 1 || g.cell_scale_ > kMaxCellScale)
    fail_archive(archive, "meta 'graph': cell_scale " + std::to_string(g.cell_scale_) + " is outside 1.." +
                              std::to_string(kMaxCellScale));
  if (A < 0 || E < 0 || A > std::numeric_limits<int32_t>::max() || E > std::numeric_limits<int32_t>::max())
    fail_archive(archive, "meta 'graph': anchors/entries out of range");
  // get() names the array and the file when dtype or shape disagree with the meta.
  g.row_offsets_ = archive.get<int32_t>("graph/row_offsets", {A + 1});
  g.neighbours_ = archive.get<int32_t>("graph/neighbours", {E});
  try {
    g.validate("array 'graph/...'");
  } catch (const std::logic_error& e) {
    fail_archive(archive, e.what());
  }
  return g;
}

}  // namespace ag2gs
