// intersection-v0's frame of one world in C++: the roundabout's act() (routed_model.h),
// then every `every` road frames the right-of-way pass of torchrl_grpo/sim/regulation.py,
// the motion, and the collisions in road.vehicles order (intersection.py), where the ego
// comes after `ego_rank` of the others. Expressions keep the tensor path's operation
// order, as in routed_native.cpp.
#pragma once
#include <memory>
#include <vector>

#include "routed_model.h"

namespace highway {

// Field order and types mirror intersection_native.py's RulesParams.
struct RulesParams {
  double every, n_times, rect_length, rect_width;  // the rectangles' full sizes (m)
  double times[16];  // the prediction times (s)
  const int64_t* priority;  // [lanes]
};

// Yield states (regulation.py): never yielded, yielded and released, yielding now.
enum Yield : int8_t { NEVER = 0, YIELDED = 1, YIELDING = 2 };

template <class T>
struct IntersectionModel : RoutedModel<T> {
  const RulesParams& q;
  int times;
  std::vector<T> px, py, ph;  // [n, times]: predicted positions and headings
  std::vector<int64_t> leg_lane;  // one vehicle's remaining legs as lanes
  std::vector<int> order;  // rows in road.vehicles order
  std::vector<char> yields;
  std::vector<T> ox, oy, oh, ov, oix, oiy;  // the collision pass's rows, in road order
  std::unique_ptr<bool[]> flags;  // their crashed, impact, checks, present: 4 x n

  IntersectionModel(const RoutedParams& p, const RulesParams& rules, int n)
      : RoutedModel<T>(p, n), q(rules), times(int(rules.n_times)), flags(new bool[4 * n]) {
    for (auto* v : {&px, &py, &ph}) v->resize(size_t(n) * times);
    leg_lane.resize(std::max<int64_t>(p.route_length, 1));
    order.resize(n), yields.resize(n);
    for (auto* v : {&ox, &oy, &oh, &ov, &oix, &oiy}) v->resize(n);
  }

  // predict_along_route of row k: s on its current lane plus speed x t, walked along
  // the legs from its route's head (a road leg takes the lane of k's lane id).
  void predict(const World<T>& w, const Routes<T>& routes, int k) {
    const RoutedParams& p = this->p;
    const Lanes<T>& lanes = this->lanes;
    const int64_t legs = p.route_length, own = p.lane_id[w.lane[k]];
    T s0, r0;
    lanes.local(w.x[k], w.y[k], w.lane[k], s0, r0);
    int64_t count = 0;
    for (int64_t m = 0; m < legs; ++m) {
      const int64_t leg = routes.leg_at(k, routes.head[k] + m);
      count += leg >= 0;
      leg_lane[m] = leg < p.lanes ? leg : p.road_lanes[(leg - p.lanes) * p.width_max + own];
    }
    if (count == 0)
      for (int64_t m = 0; m < legs; ++m) leg_lane[m] = w.lane[k];
    count = std::max<int64_t>(count, 1);
    for (int t = 0; t < times; ++t) {
      T s = s0 + w.v[k] * T(q.times[t]);
      int64_t at = 0;
      for (int64_t m = 0; m + 1 < legs; ++m) {
        const T here = lanes.g(std::max<int64_t>(leg_lane[m], 0), LENGTH);
        if (at == m && count > m + 1 && s > here) s = s - here, at += 1;
      }
      const int64_t lane = std::max<int64_t>(leg_lane[at], 0);
      const size_t c = size_t(k) * times + t;
      lanes.position(s, T(0), lane, px[c], py[c]);
      ph[c] = lanes.heading_at(s, lane);
    }
  }

  // rect_corners(include_midpoints=True, include_center=True) of a predicted rectangle.
  void corners(size_t c, T* cx, T* cy) const {
    const T hl = T(q.rect_length / 2), hw = T(q.rect_width / 2), z = T(0);
    const T ux[9] = {-hl, -hl, hl, hl, z, -hl, hl, z, z};
    const T uy[9] = {-hw, hw, hw, -hw, z, z, z, -hw, hw};
    const T cs = std::cos(ph[c]), sn = std::sin(ph[c]);
    for (int e = 0; e < 9; ++e) {
      cx[e] = (cs * ux[e] + (-sn) * uy[e]) + px[c];
      cy[e] = (sn * ux[e] + cs * uy[e]) + py[c];
    }
  }
  // Any of the 9 points in the rectangle at c (point_in_rotated_rectangle turns by +angle).
  bool inside(const T* cx, const T* cy, size_t c) const {
    const T hl = T(q.rect_length / 2), hw = T(q.rect_width / 2);
    const T cs = std::cos(ph[c]), sn = std::sin(ph[c]);
    for (int e = 0; e < 9; ++e) {
      const T dx = cx[e] - px[c], dy = cy[e] - py[c];
      const T ux = cs * dx + (-sn) * dy, uy = sn * dx + cs * dy;
      if (-hl <= ux && ux <= hl && -hw <= uy && uy <= hw) return true;
    }
    return false;
  }
  bool conflict(int i, int j) const {  // is_conflict_possible
    T cx[9], cy[9];
    for (int t = 0; t < times; ++t) {
      const size_t a = size_t(i) * times + t, b = size_t(j) * times + t;
      const T dx = px[b] - px[a], dy = py[b] - py[a];
      if (std::sqrt(dx * dx + dy * dy) > T(this->p.length)) continue;
      corners(a, cx, cy);
      if (inside(cx, cy, b)) return true;
      corners(b, cx, cy);
      if (inside(cx, cy, a)) return true;
    }
    return false;
  }

  // enforce_road_rules: release the yielding vehicles, then in every conflicting pair
  // (i before j in road order) the one of lower priority, or behind at equal priority,
  // yields unless it is the ego (row 0).
  void enforce(World<T>& w, const Routes<T>& routes, int8_t* yielding) {
    const int n = this->n;
    for (int k = 0; k < n; ++k)
      if (w.present[k]) predict(w, routes, k);
    std::fill(yields.begin(), yields.end(), 0);
    for (int a = 0; a < n; ++a) {
      const int i = order[a];
      if (!w.present[i]) continue;
      for (int b = a + 1; b < n; ++b) {
        const int j = order[b];
        if (!w.present[j] || !conflict(i, j)) continue;
        const int64_t pi = q.priority[w.lane[i]], pj = q.priority[w.lane[j]];
        const T dx = w.x[j] - w.x[i], dy = w.y[j] - w.y[i];
        const T ci = std::cos(w.h[i]), si = std::sin(w.h[i]);
        const T cj = std::cos(w.h[j]), sj = std::sin(w.h[j]);
        const T ahead_i = std::fma(si, dy, ci * dx), ahead_j = std::fma(sj, -dy, cj * -dx);
        yields[pi < pj || (pi == pj && ahead_i > ahead_j) ? i : j] = 1;
      }
    }
    for (int k = 0; k < n; ++k) {
      if (yielding[k] == YIELDING) w.vt[k] = T(this->p.speed_limit), yielding[k] = YIELDED;
      if (yields[k] && w.present[k] && k != 0) w.vt[k] = T(0), yielding[k] = YIELDING;
    }
  }

  // handle_collisions over pairs in road order: the rows copied in that order, collided,
  // and their flags and impacts put back.
  void collide_in_order(World<T>& w) {
    const int n = this->n;
    bool *crashed = flags.get(), *impact = crashed + n, *checks = impact + n, *present = checks + n;
    for (int a = 0; a < n; ++a) {
      const int r = order[a];
      ox[a] = w.x[r], oy[a] = w.y[r], oh[a] = w.h[r], ov[a] = w.v[r];
      oix[a] = w.ix[r], oiy[a] = w.iy[r];
      crashed[a] = w.crashed[r], impact[a] = w.impact[r];
      checks[a] = w.checks[r], present[a] = w.present[r];
    }
    World<T> ordered{ox.data(), oy.data(), oh.data(), ov.data(), nullptr, nullptr, nullptr,
                     nullptr, nullptr, oix.data(), oiy.data(), nullptr, nullptr, crashed,
                     impact, checks, present, n};
    collide(this->collision, ordered);
    for (int a = 0; a < n; ++a) {
      const int r = order[a];
      w.crashed[r] = crashed[a], w.impact[r] = impact[a], w.ix[r] = oix[a], w.iy[r] = oiy[a];
    }
  }

  void substep(World<T>& w, Routes<T>& routes, int64_t action, bool first, int64_t& speed_index,
               int64_t& road_steps, int8_t* yielding) {
    const RoutedParams& p = this->p;
    this->ego_act(w, routes, first ? action : -1, first, speed_index);
    this->others_act(w, routes);
    road_steps += 1;
    if (road_steps % int64_t(q.every) == 0) enforce(w, routes, yielding);
    move_rows(w, T(p.dt), T(p.max_speed), T(p.min_speed), T(p.length / 2),
              [this](T x, T y, T h, int64_t was) { return this->lanes.closest(x, y, h, was); });
    collide_in_order(w);
  }

  // The first `used` rows (at most the table's), in road order: intersection.py's road_order.
  void use_rows(int used, int64_t ego_rank) {
    this->n = this->o = used;
    ego_rank = std::min<int64_t>(ego_rank, used - 1);  // the same order of the present rows
    for (int k = 0; k < used; ++k) order[k] = k < ego_rank ? k + 1 : (k == ego_rank ? 0 : k);
  }
};

}  // namespace highway
