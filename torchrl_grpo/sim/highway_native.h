// What the C++ highway step shares: the constants, the column pointers, one world's rows
// and the scalar helpers of torchrl_grpo/sim/road.py. See highway_native.cpp.
#pragma once
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <thread>
#include <vector>

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
  double feature[16], ranged[16], low[16], high[16];  // MAX_FEATURES
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

// World b's rows of the [B, n] columns of `t`.
template <class T>
World<T> rows_of(const Table& t, int64_t b, int n) {
  auto f = [&](void* col) { return static_cast<T*>(col) + b * n; };
  return {f(t.x), f(t.y), f(t.heading), f(t.speed), f(t.target_speed), f(t.steering),
          f(t.acceleration), f(t.timer), f(t.delta), f(t.impact_x), f(t.impact_y),
          t.lane + b * n, t.target_lane + b * n, t.crashed + b * n, t.impact + b * n,
          t.check_collisions + b * n, t.present + b * n, n};
}

// Vehicle.step(dt) of every row, padding included (kinematics.py); `closest(x, y, h,
// lane before)` is the lane a vehicle ends on.
template <class T, class Closest>
void move_rows(World<T>& w, T dt, T top, T bottom, T half_length, const Closest& closest) {
  for (int i = 0; i < w.n; ++i) {
    T steering = w.crashed[i] ? T(0) : w.steer[i];
    T a = w.crashed[i] ? w.v[i] * T(-1) : w.acc[i];
    if (w.v[i] > top)
      a = std::min(a, (top - w.v[i]) * T(1));
    else if (w.v[i] < bottom)
      a = std::max(a, (bottom - w.v[i]) * T(1));
    T beta = std::atan(std::tan(steering) * T(0.5));
    T x = w.x[i] + (w.v[i] * std::cos(w.h[i] + beta)) * dt;
    T y = w.y[i] + (w.v[i] * std::sin(w.h[i] + beta)) * dt;
    if (w.impact[i]) x = x + w.ix[i], y = y + w.iy[i];
    T h = w.h[i] + ((w.v[i] * std::sin(beta)) / half_length) * dt;
    if (i > 0) w.timer[i] = w.timer[i] + dt;  // the ego has no MOBIL timer
    w.x[i] = x, w.y[i] = y, w.h[i] = h;
    w.v[i] = w.v[i] + a * dt;
    w.steer[i] = steering, w.acc[i] = a;
    w.ix[i] = w.iy[i] = T(0);
    w.lane[i] = closest(x, y, h, w.lane[i]);
    w.crashed[i] = w.crashed[i] || w.impact[i];
    w.impact[i] = false;
  }
}

// fn(lo, hi) over blocks of 32 of `batch` worlds on up to `threads` threads. Threads take
// blocks as they free up, so that a thread on a core another process shares does not
// hold the others back (a world's result does not depend on which thread steps it).
template <class F>
void for_blocks(int64_t batch, int64_t threads, const F& fn) {
  const int64_t block = 32;
  std::atomic<int64_t> next{0};
  auto run = [&]() {
    for (int64_t lo; (lo = next.fetch_add(block)) < batch;) fn(lo, std::min(batch, lo + block));
  };
  int64_t workers = std::max<int64_t>(1, std::min<int64_t>(threads, (batch + block - 1) / block));
  std::vector<std::thread> pool;
  for (int64_t k = 1; k < workers; ++k) pool.emplace_back(run);
  run();
  for (auto& th : pool) th.join();
}

}  // namespace highway
