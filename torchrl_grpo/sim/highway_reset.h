// Fresh highway worlds in C++, drawn as torchrl_grpo/sim/reset.py and
// envs/highway/tensor_state.py's fresh_highway_words draw them: the same counter-based
// stream (rng.py's SplitMix64 hash of key, counter and draw index), the same float64
// arithmetic, so a reset row holds the tensor path's bits.
#pragma once
#include "highway_native.h"

namespace highway {

inline uint64_t mix64(uint64_t x) {  // SplitMix64's finaliser
  x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ULL;
  x = (x ^ (x >> 27)) * 0x94D049BB133111EBULL;
  return x ^ (x >> 31);
}

// Draw `index` of the call `counter` of the stream `key`, uniform in [0, 1) (rng.uniform).
inline double draw(int64_t key, int64_t counter, int64_t index) {
  const uint64_t golden = 0x9E3779B97F4A7C15ULL, per_call = uint64_t(1) << 20;
  uint64_t word = (uint64_t(counter) * per_call + uint64_t(index)) * golden;
  word = mix64(mix64(word + uint64_t(key)) ^ uint64_t(key));
  return double(int64_t(word >> 11)) * 0x1p-53;
}

inline double floor_mod(double a, double b) {  // torch.remainder
  double m = std::fmod(a, b);
  if (m != 0 && ((b < 0) != (m < 0))) m += b;
  return m;
}

// One fresh world into w (reset_world's _fresh_rows), its stream advanced by two calls,
// and the highway-env generator words it carries (`words`, 10 of them).
template <class T>
void fresh_world(const Params& p, World<T>& w, int64_t key, int64_t& counter, int64_t* words) {
  const int64_t call = counter;
  const double lanes = p.lanes_count, width = p.lane_width;
  const int64_t ego_lane = p.initial_lane >= 0 ? int64_t(p.initial_lane)
                                               : int64_t(std::floor(draw(key, call, 0) * lanes));
  const double ego_x = (draw(key, call, 1) * p.jitter_span + p.jitter_lo) * p.ego_offset + p.ego_base;
  double ahead = 0;
  for (int j = 0; j < w.n; ++j) {
    double x = ego_x, speed = p.ego_speed, target = p.ego_target, delta = 0;
    int64_t lane = ego_lane;
    if (j > 0) {
      const int64_t at = 2 + 4 * (j - 1);  // lane, speed, jitter, delta of vehicle j
      speed = draw(key, call, at + 1) * p.speed_span + p.speed_lo;
      double offset = ((speed * p.spacing_per_speed + p.spacing_base) * p.inv_density) * p.decay;
      ahead = ahead + offset * (draw(key, call, at + 2) * p.jitter_span + p.jitter_lo);
      x = ego_x + ahead;
      lane = int64_t(std::floor(draw(key, call, at) * lanes));
      delta = draw(key, call, at + 3) * p.delta_span + p.delta_lo;
      target = speed;
    }
    double y = double(lane) * width;
    w.x[j] = T(x), w.y[j] = T(y), w.v[j] = T(speed), w.vt[j] = T(target), w.delta[j] = T(delta);
    w.timer[j] = T(j == 0 ? 0.0 : floor_mod((x + y) * M_PI, p.lane_change_delay));
    w.h[j] = w.steer[j] = w.acc[j] = w.ix[j] = w.iy[j] = T(0);
    w.lane[j] = w.target[j] = lane;
    w.crashed[j] = w.impact[j] = false;
    w.checks[j] = j == 0 || p.others_check_collisions != 0;
    w.present[j] = true;
  }
  for (int k = 0; k < 8; ++k) words[k] = int64_t(draw(key, call + 1, k) * 4294967296.0);
  words[4] |= 1;
  words[8] = words[9] = 0;
  counter = call + 2;
}

}  // namespace highway
