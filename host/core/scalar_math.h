// The scalar activations the host applies to model parameters, one copy
// each: the kernels' (kernels/common.cl) in double precision.
#pragma once

#include <cmath>

namespace ag2gs {

// log(p / (1 - p)): the logit of an opacity or a scale fraction.
inline double logit(double p) {
  return std::log(p / (1.0 - p));
}

inline double sigmoid(double x) {
  return 1.0 / (1.0 + std::exp(-x));
}

// Single precision, as the free-Gaussian trainer's host code has always
// computed it (a separate name, so float arguments never pick it silently).
inline float sigmoidf(float x) {
  return 1.f / (1.f + std::exp(-x));
}

}  // namespace ag2gs
