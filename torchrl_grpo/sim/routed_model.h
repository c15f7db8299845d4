// The merge-v0 and roundabout-v0 frame of one world in C++, shared by routed_native.cpp
// (merge, roundabout) and intersection_rules.h (intersection-v0, which adds its rules):
// the ego's and the IDM vehicles' act() on the road graph, kinematics, every pair's
// collision, merge's obstacle. See routed_native.cpp for the conventions.
#pragma once
#include <vector>

#include "highway_collide.h"
#include "highway_native.h"
#include "routed_road.h"

namespace highway {
template <class T>
struct RoutedModel {
  const RoutedParams& p;
  Params collision;  // the fields collide() reads
  Lanes<T> lanes;
  int n;
  int o;  // the obstacle's row (n: none), which never acts nor moves
  T obstacle_reach;  // a car's and the obstacle's mean diagonal, merge.py's prefilter
  std::vector<T> cos_h, sin_h, s_own, r_own, s_in, r_in;

  RoutedModel(const RoutedParams& params, int vehicles)
      : p(params), collision(), lanes(params), n(vehicles) {
    o = int(std::min<int64_t>(p.obstacle_row, n));
    const double car = std::sqrt(p.length * p.length + p.width * p.width);
    const double obstacle =
        std::sqrt(p.obstacle_length * p.obstacle_length + p.obstacle_width * p.obstacle_width);
    obstacle_reach = T((car + obstacle) / 2);
    collision.length = p.length, collision.width = p.width, collision.dt = p.dt;
    collision.others_check_collisions = p.others_check_collisions;
    for (auto* v : {&cos_h, &sin_h, &s_own, &r_own, &s_in, &r_in}) v->resize(n);
  }

  void frames_in(const World<T>& w, int64_t lane, T* s, T* r) const {  // every row in `lane`
    for (int j = 0; j < n; ++j) lanes.local(w.x[j], w.y[j], lane, s[j], r[j]);
  }

  // Road.neighbour_vehicles(k, lane) from every row's (s, r) in that lane: the front is
  // the smallest s >= k's (ties: the last row), the rear the largest s < k's (the first).
  void neighbours(const World<T>& w, int k, int64_t lane, const T* s, const T* r, int& front,
                  int& rear) const {
    front = rear = -1;
    const T mine = s[k];
    for (int j = 0; j < n; ++j) {
      if (j == k || !w.present[j] || !lanes.on_lane(s[j], r[j], lane, T(1))) continue;
      if (mine <= s[j]) {
        if (front < 0 || s[j] <= s[front]) front = j;
      } else if (rear < 0 || s[j] > s[rear]) {
        rear = j;
      }
    }
  }

  T free_road(const World<T>& w, int i, T delta) const {
    T target = clamp(w.vt[i], T(0), T(p.speed_limit));
    T ratio = std::max(w.v[i], T(0)) / std::fabs(not_zero(target));
    return T(p.comfort_acc_max) * (T(1) - std::pow(ratio, delta));
  }
  T gap(const World<T>& w, int e, int f) const {  // desired_gap(e, f)
    T dvx = w.v[e] * cos_h[e] - w.v[f] * cos_h[f];
    T dvy = w.v[e] * sin_h[e] - w.v[f] * sin_h[f];
    T dv = dvx * cos_h[e] + dvy * sin_h[e];
    return (T(p.distance_wanted) + w.v[e] * T(p.time_wanted)) +
           (w.v[e] * dv) / T(2 * std::sqrt(-p.comfort_acc_max * p.comfort_acc_min));
  }
  T interaction(const World<T>& w, int e, T s_e, int f, T s_f) const {
    T term = gap(w, e, f) / not_zero(s_f - s_e);
    return T(p.comfort_acc_max) * (term * term);
  }
  // IDM of k behind `front` (-1: none), both placed along k's own lane.
  T behind(const World<T>& w, int k, int front, T free) const {
    return front < 0 ? free - T(0) : free - interaction(w, k, s_own[k], front, s_own[front]);
  }

  T steer(const World<T>& w, int k, int64_t target) const {  // steering_control(target)
    T s, r;
    lanes.local(w.x[k], w.y[k], target, s, r);
    T future = lanes.heading_at(s + w.v[k] * T(p.tau_pursuit), target);
    T v_nz = not_zero(w.v[k]);
    T heading_cmd = std::asin(clamp((T(-p.kp_lateral) * r) / v_nz, T(-1), T(1)));
    T heading_ref = future + clamp(heading_cmd, T(-M_PI / 4), T(M_PI / 4));
    T rate = T(p.kp_heading) * wrap_to_pi(heading_ref - w.h[k]);
    T slip = ((T(1) / v_nz) * T(p.length / 2)) * rate;
    T steering = std::atan(T(2) * std::tan(std::asin(clamp(slip, T(-1), T(1)))));
    return clamp(steering, T(-p.max_steering_angle), T(p.max_steering_angle));
  }

  // IDMVehicle.mobil(cand) with the route rule; `decided` is k's target so far.
  bool mobil(const World<T>& w, Routes<T>& routes, int k, int64_t cand, T acc_now, T free,
             int64_t decided) {
    frames_in(w, cand, s_in.data(), r_in.data());
    int new_front, new_rear;
    neighbours(w, k, cand, s_in.data(), r_in.data(), new_front, new_rear);
    T pred = T(0) - T(0);
    if (new_rear >= 0 && new_rear < o) {  // the new follower (a vehicle, not the obstacle)
      // brakes for k along ITS lane, with k's exponent
      const int64_t rear_lane = w.lane[new_rear];
      T s_rear, s_me, unused;
      lanes.local(w.x[new_rear], w.y[new_rear], rear_lane, s_rear, unused);
      lanes.local(w.x[k], w.y[k], rear_lane, s_me, unused);
      pred = free_road(w, new_rear, w.delta[k]) - interaction(w, new_rear, s_rear, k, s_me);
    }
    const bool unsafe = pred < -T(p.max_braking_imposed);
    const T mine = behind(w, k, new_front, free);
    const int64_t wanted = routes.wanted_id(k);
    if (wanted < 0) return !unsafe && !((mine - acc_now) < T(p.min_acc_gain));
    const int64_t now = p.lane_id[decided], there = p.lane_id[cand];
    auto sign = [](int64_t a) { return (a > 0) - (a < 0); };
    const bool side = sign(there - now) == sign(wanted - now);
    return !unsafe && side && !(mine < -T(p.max_braking_imposed));
  }

  bool aborts(const World<T>& w, int k, int64_t follow) const {  // the abort scan of k
    for (int j = 0; j < n; ++j) {
      if (j == k || j >= o || w.lane[j] == follow || w.target[j] != follow) continue;
      T d = s_own[j] - s_own[k];
      if (T(0) < d && d < gap(w, k, j)) return true;
    }
    return false;
  }

  void ego_act(World<T>& w, Routes<T>& routes, int64_t action, bool first,
               int64_t& speed_index) const {
    int64_t target = routes.follow(0, w.x[0], w.y[0], w.target[0]);
    if (action == 0 || action == 2) {
      const int64_t cand = action == 0 ? p.left[target] : p.right[target];
      T s, r;
      lanes.local(w.x[0], w.y[0], cand, s, r);
      if (lanes.reachable(s, r, cand)) target = cand;
    }
    const int step = action == 3 ? 1 : (action == 4 ? -1 : 0);
    if (step != 0) {
      const int k = int(p.n_speeds);
      T ratio = (w.v[0] - T(p.speeds[0])) / T(p.speeds[k - 1] - p.speeds[0]);
      T index = clamp(std::nearbyint(ratio * T(k - 1)), T(0), T(k - 1));
      const int moved = std::min(std::max(int(index) + step, 0), k - 1);
      speed_index = moved, w.vt[0] = T(p.speeds[moved]);
    }
    if (first) target = routes.follow(0, w.x[0], w.y[0], target);
    w.target[0] = target;
    w.steer[0] = steer(w, 0, target);
    w.acc[0] = T(p.kp_a) * (w.vt[0] - w.v[0]);
  }

  void others_act(World<T>& w, Routes<T>& routes) {
    for (int j = 0; j < n; ++j) cos_h[j] = std::cos(w.h[j]), sin_h[j] = std::sin(w.h[j]);
    for (int k = 1; k < o; ++k) {
      if (w.crashed[k]) continue;  // crashed vehicles skip act(): targets and routes stay
      const int64_t lane = w.lane[k];
      const int64_t follow = routes.follow(k, w.x[k], w.y[k], w.target[k]);
      const bool changing = lane != follow;
      frames_in(w, lane, s_own.data(), r_own.data());
      const T free = free_road(w, k, w.delta[k]);
      int front, rear;
      neighbours(w, k, lane, s_own.data(), r_own.data(), front, rear);
      T acc = behind(w, k, front, free);
      int64_t decided = follow;
      const bool due = !changing && T(p.lane_change_delay) < w.timer[k];
      if (due) {
        w.timer[k] = T(0);
        const bool moving = !(std::fabs(w.v[k]) < T(1));
        for (const int64_t* side : {p.side_left, p.side_right}) {  // right wins
          const int64_t cand = side[lane];
          if (cand < 0 || !moving) continue;
          T s, r;
          lanes.local(w.x[k], w.y[k], cand, s, r);
          if (lanes.reachable(s, r, cand) && mobil(w, routes, k, cand, acc, free, decided))
            decided = cand;
        }
      }
      const bool same_road = p.lane_road[lane] == p.lane_road[follow];
      const int64_t target = changing && same_road && aborts(w, k, follow) ? lane : decided;
      w.target[k] = target;
      w.steer[k] = steer(w, k, target);
      if (lane != target) {  // also brake for the target lane's front vehicle
        frames_in(w, target, s_in.data(), r_in.data());
        int target_front;
        neighbours(w, k, target, s_in.data(), r_in.data(), target_front, rear);
        acc = std::min(acc, behind(w, k, target_front, free));
      }
      w.acc[k] = clamp(acc, -T(p.acc_max), T(p.acc_max));
    }
  }

  void substep(World<T>& w, Routes<T>& routes, int64_t action, bool first,
               int64_t& speed_index) {
    ego_act(w, routes, first ? action : -1, first, speed_index);
    others_act(w, routes);
    World<T> cars = w;
    cars.n = o;
    move_rows(cars, T(p.dt), T(p.max_speed), T(p.min_speed), T(p.length / 2),
              [this](T x, T y, T h, int64_t was) { return lanes.closest(x, y, h, was); });
    collide(collision, cars);
    if (o < n) collide_obstacle(w);
  }

  // Each vehicle with merge's obstacle, after the pairs: a predicted overlap is the
  // vehicle's whole translation, replacing any other impact.
  void collide_obstacle(World<T>& w) const {
    for (int i = 0; i < o; ++i) {
      T dx = w.x[o] - w.x[i], dy = w.y[o] - w.y[i];
      T reach = obstacle_reach + w.v[i] * T(p.dt);
      if (std::sqrt(std::fma(dy, dy, dx * dx)) > reach || !(w.checks[i] || w.checks[o])) continue;
      bool hit, will;
      T tx, ty;
      separating_axes(collision, w, i, o, hit, will, tx, ty, p.obstacle_length, p.obstacle_width);
      if (hit) w.crashed[i] = w.crashed[o] = true;
      if (will) w.impact[i] = true, w.ix[i] = tx, w.iy[i] = ty;
    }
  }
};

}  // namespace highway
