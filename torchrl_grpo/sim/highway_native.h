// What the C++ highway step shares: the constants, the column pointers, one world's rows
// and the scalar helpers of torchrl_grpo/sim/road.py. See highway_native.cpp.
#pragma once
#include <algorithm>
#include <cmath>
#include <cstdint>

namespace highway {

// Field order and types mirror native.py's NativeParams.
struct Params {
  double lanes_count, lane_width, lane_length, speed_limit, margin_length;
  double length, width, max_speed, min_speed;
  double acc_max, comfort_acc_max, comfort_acc_min, distance_wanted, time_wanted;
  double politeness, min_acc_gain, max_braking_imposed, lane_change_delay;
  double kp_a, kp_heading, kp_lateral, max_steering_angle;
  double frames, dt, others_check_collisions, n_speeds;
  double speeds[16];
  // The Kinematics observation: feature codes index FEATURES of observation.py.
  double obs_count, obs_features, normalize, absolute, clip, see_behind, perception;
  double feature[8], ranged[8], low[8], high[8];
  // Fresh worlds (reset.py): the constants it derives in Python double, passed as such.
  double initial_lane, ego_speed, ego_index, ego_target, ego_offset, ego_base;
  double speed_lo, speed_span, spacing_base, spacing_per_speed, inv_density, decay;
  double jitter_lo, jitter_span, delta_lo, delta_span;
};

// Column pointers of the [B, N] vehicle table and the [B] words (native.py's NativeTable).
struct Table {
  void *x, *y, *heading, *speed, *target_speed, *steering, *acceleration, *timer, *delta,
      *impact_x, *impact_y;
  int64_t *lane, *target_lane;
  bool *crashed, *impact, *check_collisions, *present;
  int64_t *speed_index, *steps, *action;
};

template <class T>
struct World {  // one world's n rows of the vehicle table
  T *x, *y, *h, *v, *vt, *steer, *acc, *timer, *delta, *ix, *iy;
  int64_t *lane, *target;
  bool *crashed, *impact, *checks, *present;
  int n;
};

template <class T>
T clamp(T a, T lo, T hi) {  // torch.clamp
  return std::min(std::max(a, lo), hi);
}

template <class T>
T not_zero(T a) {  // utils.not_zero, eps in T
  const T eps = T(1e-2);
  return std::fabs(a) > eps ? a : (a >= 0 ? eps : -eps);
}

template <class T>
T wrap_to_pi(T a) {  // torch.remainder(a + pi, 2 pi) - pi: a floor modulo, pi in T
  const T pi = T(M_PI), two_pi = T(2 * M_PI);
  T m = std::fmod(a + pi, two_pi);
  if (m != 0 && ((two_pi < 0) != (m < 0))) m += two_pi;
  return m - pi;
}

}  // namespace highway
