// A road graph in C++: the lane geometry of torchrl_grpo/sim/lanes.py, and the hand-over
// at a lane's end: merge.py's fixed next lane, or routes.py's route following. One world
// at a time; see routed_native.cpp.
#pragma once
#include <cstdint>
#include <limits>

#include "highway_native.h"

namespace highway {

// Field order and types mirror routed_native.py's RoutedParams.
struct RoutedParams {
  double frames, dt, length, width, max_speed, min_speed;
  double acc_max, comfort_acc_max, comfort_acc_min, distance_wanted, time_wanted;
  double min_acc_gain, max_braking_imposed, lane_change_delay;
  double kp_a, kp_heading, kp_lateral, max_steering_angle, tau_pursuit, speed_limit;
  double others_check_collisions, n_speeds, obstacle_length, obstacle_width;
  double speeds[16];
  int64_t lanes, roads, width_max, fanout, route_length, obstacle_row;
  const double* geometry;  // [lanes, 19]: LaneGeometry's fields in their order
  const int64_t *lane_id, *lane_road, *left, *right, *side_left, *side_right;  // [lanes]
  const int64_t* next_lane;  // [lanes]: the fixed hand-over (merge-v0; null with routes)
  const int64_t *road_from, *road_to, *road_count;  // [roads] (routes only)
  const int64_t *road_lanes, *next_roads;  // [roads, width_max], [roads, fanout]
};

// Columns of RoutedParams.geometry (LaneGeometry's field order).
enum Geo {
  KIND, START_X, START_Y, DIR_X, DIR_Y, LAT_X, LAT_Y, HEADING, LENGTH, WIDTH,
  AMPLITUDE, PULSATION, PHASE, CENTER_X, CENTER_Y, RADIUS, START_PHASE, TURN, FORBIDDEN,
  GEO_COLUMNS
};

// lanes.py's functions on one lane; each constant is rounded to T first, as the tensor
// path gathers the lane table in the worlds' dtype. addcmul is fused (std::fma) as
// torch computes it on the CPU.
template <class T>
struct Lanes {
  const RoutedParams& p;
  explicit Lanes(const RoutedParams& params) : p(params) {}

  T g(int64_t lane, int column) const { return T(p.geometry[lane * GEO_COLUMNS + column]); }
  bool round(int64_t lane) const { return p.geometry[lane * GEO_COLUMNS + KIND] == 1; }
  bool plain(int64_t lane) const {  // straight: no trigonometry, the same bits
    return !round(lane) && p.geometry[lane * GEO_COLUMNS + AMPLITUDE] == 0;
  }

  // A circular lane's lateral coordinate from the offset (cx, cy) to its centre.
  T ring_r(T cx, T cy, int64_t l) const {
    return g(l, TURN) * (g(l, RADIUS) - std::sqrt(std::fma(cy, cy, cx * cx)));
  }
  void local(T x, T y, int64_t l, T& s, T& r) const {  // local_coordinates
    if (round(l)) {
      T cx = x - g(l, CENTER_X), cy = y - g(l, CENTER_Y), start = g(l, START_PHASE);
      T phi = start + wrap_to_pi(std::atan2(cy, cx) - start);
      s = (g(l, TURN) * (phi - start)) * g(l, RADIUS);
      r = ring_r(cx, cy, l);
      return;
    }
    T dx = x - g(l, START_X), dy = y - g(l, START_Y);
    s = std::fma(dy, g(l, DIR_Y), dx * g(l, DIR_X));
    r = std::fma(dy, g(l, LAT_Y), dx * g(l, LAT_X));
    if (!plain(l)) r = r - g(l, AMPLITUDE) * std::sin(g(l, PULSATION) * s + g(l, PHASE));
  }
  void position(T s, T r, int64_t l, T& x, T& y) const {
    if (round(l)) {
      T phi = (g(l, TURN) * s) / g(l, RADIUS) + g(l, START_PHASE);
      T rho = g(l, RADIUS) - r * g(l, TURN);
      x = g(l, CENTER_X) + rho * std::cos(phi), y = g(l, CENTER_Y) + rho * std::sin(phi);
      return;
    }
    T sine = plain(l) ? r : r + g(l, AMPLITUDE) * std::sin(g(l, PULSATION) * s + g(l, PHASE));
    x = (g(l, START_X) + s * g(l, DIR_X)) + sine * g(l, LAT_X);
    y = (g(l, START_Y) + s * g(l, DIR_Y)) + sine * g(l, LAT_Y);
  }
  T heading_at(T s, int64_t l) const {
    if (round(l)) {
      T phi = (g(l, TURN) * s) / g(l, RADIUS) + g(l, START_PHASE);
      return phi + T(M_PI / 2) * g(l, TURN);
    }
    if (plain(l)) return g(l, HEADING);
    T slope = (g(l, AMPLITUDE) * g(l, PULSATION)) * std::cos(g(l, PULSATION) * s + g(l, PHASE));
    return g(l, HEADING) + std::atan(slope);
  }
  bool on_lane(T s, T r, int64_t l, T margin) const {
    const T vehicle = T(5);
    return std::fabs(r) <= g(l, WIDTH) / T(2) + margin && -vehicle <= s &&
           s < g(l, LENGTH) + vehicle;
  }
  bool reachable(T s, T r, int64_t l) const {  // is_reachable_from
    bool close = std::fabs(r) <= T(2) * g(l, WIDTH) && T(0) <= s && s < g(l, LENGTH) + T(5);
    return close && p.geometry[l * GEO_COLUMNS + FORBIDDEN] == 0;
  }
  bool after_end(T s, int64_t l) const { return s > g(l, LENGTH) - T(2.5); }
  T distance(T s, T r, int64_t l) const {  // lane.distance from (s, r)
    return (std::fabs(r) + std::max(s - g(l, LENGTH), T(0))) + std::max(T(0) - s, T(0));
  }
  T lane_distance(T x, T y, int64_t l) const {
    T s, r;
    local(x, y, l, s, r);
    return distance(s, r, l);
  }
  T distance_with_heading(T x, T y, T h, int64_t l) const {
    T s, r;
    local(x, y, l, s, r);
    return distance(s, r, l) + std::fabs(wrap_to_pi(h - heading_at(s, l)));
  }
  // get_closest_lane_index: the first lane of least distance_with_heading. `hint` (the
  // lane the vehicle was on) is scored first; a circular lane whose |r| alone, a lower
  // bound of its distance with the same bits, exceeds the best so far is skipped
  // without its arctangent.
  int64_t closest(T x, T y, T h, int64_t hint) const {
    int64_t best = hint;
    T best_d = distance_with_heading(x, y, h, hint);
    for (int64_t l = 0; l < p.lanes; ++l) {
      if (l == hint) continue;
      if (round(l) && std::fabs(ring_r(x - g(l, CENTER_X), y - g(l, CENTER_Y), l)) > best_d)
        continue;
      T d = distance_with_heading(x, y, h, l);
      if (d < best_d || (d == best_d && l < best)) best = l, best_d = d;
    }
    return best;
  }
};

// One world's routes ([n, route_length] leg codes, [n] heads; null legs: no routes,
// the fixed hand-over): routes.py on one vehicle.
template <class T>
struct Routes {
  const RoutedParams& p;
  const Lanes<T>& lanes;
  const int64_t* legs;
  int64_t* head;

  int64_t leg_at(int k, int64_t h) const { return h < p.route_length ? legs[k * p.route_length + h] : -1; }
  int64_t leg_road(int64_t leg) const {
    return leg < 0 ? -1 : (leg < p.lanes ? p.lane_road[leg] : leg - p.lanes);
  }
  int64_t leg_lane_id(int64_t leg) const { return leg >= 0 && leg < p.lanes ? p.lane_id[leg] : -1; }
  int64_t wanted_id(int k) const { return legs ? leg_lane_id(leg_at(k, head[k])) : -1; }

  // network.next_lane(target, route, position), dropping a finished head leg.
  int64_t next_lane(int k, T x, T y, int64_t target) {
    const int64_t current = p.lane_road[target], end = p.road_to[current];
    int64_t leg = leg_at(k, head[k]);
    if (leg >= 0 && leg_road(leg) == current) head[k] += 1;
    leg = leg_at(k, head[k]);
    const int64_t leg_to = leg_road(leg);
    const bool follows = leg >= 0 && p.road_from[leg_to] == end;
    const int64_t same_id = follows && leg_lane_id(leg) >= 0 ? leg_lane_id(leg) : p.lane_id[target];
    T s, r, px, py;
    lanes.local(x, y, target, s, r);
    lanes.position(s, T(0), target, px, py);
    int64_t best = -1, chosen = target;
    T best_d = std::numeric_limits<T>::infinity();
    for (int64_t c = 0; c < (follows ? 1 : p.fanout); ++c) {
      const int64_t road = follows ? leg_to : p.next_roads[current * p.fanout + c];
      if (road < 0) continue;
      const int64_t* row = p.road_lanes + road * p.width_max;
      int64_t pick;
      if (p.road_count[road] == p.road_count[current]) {
        pick = row[std::min(same_id, p.width_max - 1)];
      } else {  // the first closest lane of the road
        T near_d = std::numeric_limits<T>::infinity();
        pick = row[0];
        for (int64_t w = 0; w < p.width_max && row[w] >= 0; ++w) {
          T d = lanes.lane_distance(px, py, row[w]);
          if (d < near_d) near_d = d, pick = row[w];
        }
      }
      T d = lanes.lane_distance(px, py, std::max<int64_t>(pick, 0));
      if (best < 0 || d < best_d) best = c, best_d = d, chosen = pick;
    }
    return chosen;  // no road leaves the node: the target stays (highway-env's KeyError)
  }

  // follow_road: past the target lane's end, the next lane (of the route, if any).
  int64_t follow(int k, T x, T y, int64_t target) {
    T s, r;
    lanes.local(x, y, target, s, r);
    if (!lanes.after_end(s, target)) return target;
    return legs ? next_lane(k, x, y, target) : p.next_lane[target];
  }
};

}  // namespace highway
