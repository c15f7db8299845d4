// The Kinematics observation in C++, as torchrl_grpo/sim/observation.py computes it.
#pragma once
#include <vector>

#include "highway_native.h"

namespace highway {

// KinematicObservation.observe with order="sorted" into out [obs_count, obs_features]:
// the ego, then the visible vehicles by |dx| (ties in road order), x, y, vx and vy
// relative to the ego unless absolute, normalised and clipped; missing rows are zeros.
// key and order are scratch of n entries.
template <class T>
void observe(const Params& p, const World<T>& w, T* out, std::vector<T>& key,
             std::vector<int>& order) {
  const int rows = int(p.obs_count), f = int(p.obs_features);
  int shown = 0;
  for (int j = 1; j < w.n; ++j) {
    T dx = w.x[j] - w.x[0], dy = w.y[j] - w.y[0];
    bool visible = w.present[j] && std::sqrt(dx * dx + dy * dy) < T(p.perception);
    if (!p.see_behind) visible = visible && T(-2 * p.length) < dx;
    if (!visible) continue;
    int k = shown++;  // a stable insertion sort: j is the highest index so far
    while (k > 0 && key[k - 1] > std::fabs(dx)) key[k] = key[k - 1], order[k] = order[k - 1], --k;
    key[k] = std::fabs(dx), order[k] = j;
  }
  std::fill(out, out + rows * f, T(0));
  const T c0 = std::cos(w.h[0]), s0 = std::sin(w.h[0]);
  const T ego[4] = {w.x[0], w.y[0], w.v[0] * c0, w.v[0] * s0};
  for (int r = 0; r < std::min(rows, shown + 1); ++r) {
    int j = r == 0 ? 0 : order[r - 1];
    T c = std::cos(w.h[j]), s = std::sin(w.h[j]);
    // FEATURES: presence, x, y, vx, vy, heading, cos_h, sin_h, cos_d, sin_d (no routes
    // on the highway: highway-env's destination is the position, its direction zero).
    const T values[10] = {T(1), w.x[j], w.y[j], w.v[j] * c, w.v[j] * s, w.h[j], c, s, T(0), T(0)};
    for (int q = 0; q < f; ++q) {
      int code = int(p.feature[q]);
      T value = values[code];
      if (r > 0 && !p.absolute && code >= 1 && code <= 4) value = value - ego[code - 1];
      if (p.normalize && p.ranged[q]) {
        value = ((value - T(p.low[q])) * T(2)) / T(p.high[q] - p.low[q]) + T(-1);
        if (p.clip) value = clamp(value, T(-1), T(1));
      }
      out[r * f + q] = value;
    }
  }
}

}  // namespace highway
