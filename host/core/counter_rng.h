// Counter-based random numbers: every draw is a pure function of a seed and
// the indices it belongs to, so a result never depends on the order of work,
// the thread count or how a run was split by checkpoints. One definition for
// every user (anchor initialisation, both trainers' view order, the free
// Gaussians' splits, the synthetic scenes).
#pragma once

#include <cstddef>
#include <cstdint>
#include <utility>
#include <vector>

namespace ag2gs {

// splitmix64's output function: a bijective 64-bit mixer.
inline uint64_t splitmix64(uint64_t x) {
  x += 0x9e3779b97f4a7c15ull;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ull;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebull;
  return x ^ (x >> 31);
}

// The training view of iteration `it` (0-based): each epoch of
// views.size() iterations visits every view once, in a Fisher-Yates order
// drawn from (seed, epoch). Both trainers use it, so the same seed gives
// both the same view order.
inline int epoch_shuffled_view(const std::vector<int>& views, uint64_t seed, int it) {
  const size_t n = views.size();
  const uint64_t epoch = static_cast<uint64_t>(it) / n;
  const size_t pos = static_cast<size_t>(it) % n;
  std::vector<int> perm(views);
  const uint64_t key = splitmix64(seed ^ 0x7261696e5f766965ull);
  for (size_t i = n; i > 1; --i) {  // modulo bias is negligible for n << 2^64
    const size_t j = static_cast<size_t>(splitmix64(splitmix64(key ^ epoch) ^ i) % i);
    std::swap(perm[i - 1], perm[j]);
  }
  return perm[pos];
}

}  // namespace ag2gs
