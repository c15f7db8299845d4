// One env step of B highway worlds in C++: the `frames` substeps of torchrl_grpo.sim.simulate.
//
// The same model as the Python modules it mirrors (control, idm, mobil, neighbours,
// kinematics, collision, observation), written as a loop per world: a vehicle's
// decisions scan its lane's members directly, where the tensor path sorts every world
// and compacts the vehicles that decide. Each expression keeps the Python one's
// operation order and the float type of its constants (a Python float meets a float32
// tensor as a float32), so float64 agrees with highway-env as the tensor path does,
// and float32 differs from the tensor path only where libm and torch's vectorised
// functions round differently. Worlds are split over `threads` threads.
//
// Built and loaded by torchrl_grpo/sim/native.py; no dependency beyond the C++ library.
#include "highway_collide.h"
#include "highway_native.h"
#include "highway_observe.h"
#include "highway_reset.h"

namespace highway {

template <class T>
struct Model {
  const Params& p;
  int n;
  T quarter_pi;
  std::vector<T> lane_y;  // (float)(l * width) in T, as torch computes lane centres
  std::vector<T> cos_h, sin_h, free, idm, key;
  std::vector<int> front, members, count, order;

  Model(const Params& params, int vehicles) : p(params), n(vehicles) {
    quarter_pi = T(M_PI / 4);
    for (int l = 0; l < int(p.lanes_count); ++l)
      lane_y.push_back(T(float(l) * float(p.lane_width)));
    for (auto* v : {&cos_h, &sin_h, &free, &idm, &key}) v->resize(n);
    front.resize(n), order.resize(n);
    members.resize(lane_y.size() * n), count.resize(lane_y.size());
  }

  bool along(T x, T lo_margin) const {
    return x >= lo_margin && x < T(p.lane_length + p.margin_length);
  }
  bool reachable(T x, T y, int lane) const {
    return std::fabs(y - lane_y[lane]) <= T(2 * p.lane_width) && along(x, T(0));
  }

  // Each lane's members (within lane_width / 2 + 1 of its centre, along the road),
  // sorted by x ascending then road index descending, as neighbours.py sorts them.
  void index_lanes(const World<T>& w) {
    const T half = T(p.lane_width / 2 + 1);
    std::fill(count.begin(), count.end(), 0);
    for (int j = 0; j < n; ++j) {
      if (!w.present[j] || !along(w.x[j], -T(p.margin_length))) continue;
      for (int l = 0; l < int(lane_y.size()); ++l) {
        if (!(std::fabs(w.y[j] - lane_y[l]) <= half)) continue;
        int* row = &members[l * n];
        int k = count[l]++;  // j is the highest index so far: before any equal x
        while (k > 0 && w.x[row[k - 1]] >= w.x[j]) row[k] = row[k - 1], --k;
        row[k] = j;
      }
    }
  }

  // Road.neighbour_vehicles(i, lane): front = the member with the smallest x >= x_i
  // (ties: the last in road order), rear = the largest x < x_i (ties: the first).
  void neighbours(const World<T>& w, int i, int lane, int& fr, int& re) const {
    fr = re = -1;
    const int* row = &members[lane * n];
    for (int k = 0; k < count[lane]; ++k) {
      int j = row[k];
      if (w.x[j] < w.x[i]) {
        re = j;
      } else if (j != i) {
        fr = j;
        return;
      }
    }
  }
  T free_road(const World<T>& w, int i, T delta) const {  // 0 for no vehicle
    if (i < 0) return T(0);
    T target = clamp(w.vt[i], T(0), T(p.speed_limit));
    T ratio = std::max(w.v[i], T(0)) / std::fabs(not_zero(target));
    return T(p.comfort_acc_max) * (T(1) - std::pow(ratio, delta));
  }
  T gap(const World<T>& w, int e, int f) const {  // IDMVehicle.desired_gap
    T dvx = w.v[e] * cos_h[e] - w.v[f] * cos_h[f];
    T dvy = w.v[e] * sin_h[e] - w.v[f] * sin_h[f];
    T dv = dvx * cos_h[e] + dvy * sin_h[e];
    return (w.v[e] * T(p.time_wanted) + T(p.distance_wanted)) +
           w.v[e] * dv / T(2 * std::sqrt(-p.comfort_acc_max * p.comfort_acc_min));
  }
  T interaction(const World<T>& w, int e, int f) const {  // 0 where either is missing
    if (e < 0 || f < 0) return T(0);
    T term = gap(w, e, f) / not_zero(w.x[f] - w.x[e]);
    return T(p.comfort_acc_max) * (term * term);
  }

  bool mobil(const World<T>& w, int i, int cand) const {
    int nf, nr;
    neighbours(w, i, cand, nf, nr);
    T delta = w.delta[i];
    T nr_free = free_road(w, nr, delta);
    T nr_pred = nr_free - interaction(w, nr, i);
    bool unsafe = nr_pred < -T(p.max_braking_imposed);
    T jerk = (free[i] - interaction(w, i, nf)) - idm[i];
    if (p.politeness != 0) {
      int of, orr;
      neighbours(w, i, int(w.lane[i]), of, orr);
      T nr_a = nr_free - interaction(w, nr, nf);
      T or_free = free_road(w, orr, delta);
      T or_a = or_free - interaction(w, orr, i);
      T or_pred = or_free - interaction(w, orr, of);
      jerk = jerk + T(p.politeness) * (((nr_pred - nr_a) + or_pred) - or_a);
    }
    return !unsafe && !(jerk < T(p.min_acc_gain));
  }

  bool abort_blocked(const World<T>& w, int i) const {  // the change of i is blocked
    int64_t target = w.target[i];
    for (int j = 0; j < n; ++j) {
      if (j == i || !w.present[j] || w.lane[j] == target || w.target[j] != target) continue;
      T ahead = w.x[j] - w.x[i];
      if (T(0) < ahead && ahead < gap(w, i, j)) return true;
    }
    return false;
  }

  T steer(const World<T>& w, int i) const {  // ControlledVehicle.steering_control
    T lat = w.y[i] - lane_y[w.target[i]];
    T v_nz = not_zero(w.v[i]);
    T lateral_speed = lat * T(-p.kp_lateral);
    T heading_cmd = std::asin(clamp(lateral_speed / v_nz, T(-1), T(1)));
    T heading_ref = clamp(heading_cmd, -quarter_pi, quarter_pi) + T(0);
    T rate = wrap_to_pi(heading_ref - w.h[i]) * T(p.kp_heading);
    T slip = ((T(1) / v_nz) * T(p.length / 2)) * rate;
    T slip_angle = std::asin(clamp(slip, T(-1), T(1)));
    T s = std::atan(std::tan(slip_angle) * T(2));
    return clamp(s, T(-p.max_steering_angle), T(p.max_steering_angle));
  }

  void meta_action(World<T>& w, int64_t action, int64_t& speed_index) const {
    int lanes = int(p.lanes_count);
    int shift = action == 0 ? -1 : (action == 2 ? 1 : 0);
    if (shift != 0) {
      int cand = int(std::min<int64_t>(std::max<int64_t>(w.target[0] + shift, 0), lanes - 1));
      if (reachable(w.x[0], w.y[0], cand)) w.target[0] = cand;
    }
    int step = action == 3 ? 1 : (action == 4 ? -1 : 0);
    if (step == 0) return;
    int k = int(p.n_speeds);
    T ratio = (w.v[0] - T(p.speeds[0])) / T(p.speeds[k - 1] - p.speeds[0]);
    T index = clamp(std::nearbyint(ratio * T(k - 1)), T(0), T(k - 1));
    int moved = std::min(std::max(int(index) + step, 0), k - 1);
    speed_index = moved;
    w.vt[0] = T(p.speeds[moved]);
  }

  void act(World<T>& w) {
    index_lanes(w);
    for (int i = 0; i < n; ++i) cos_h[i] = std::cos(w.h[i]), sin_h[i] = std::sin(w.h[i]);
    for (int i = 1; i < n; ++i) {
      if (!w.present[i] || w.crashed[i]) continue;
      int re;
      free[i] = free_road(w, i, w.delta[i]);
      neighbours(w, i, int(w.lane[i]), front[i], re);
      idm[i] = free[i] - interaction(w, i, front[i]);
    }
    // change_lane_policy in road order: an abort reads the targets of the vehicles
    // before it as they were just decided, and those after it as they were.
    for (int i = 1; i < n; ++i) {
      if (!w.present[i] || w.crashed[i]) continue;
      if (w.lane[i] != w.target[i]) {
        if (abort_blocked(w, i)) w.target[i] = w.lane[i];
        continue;
      }
      if (!(T(p.lane_change_delay) < w.timer[i])) continue;
      w.timer[i] = T(0);
      int lane = int(w.lane[i]);
      bool moving = !(std::fabs(w.v[i]) < T(1));
      for (int side = -1; side <= 1; side += 2) {  // left, then right: right wins
        int cand = lane + side;
        if (cand < 0 || cand >= int(p.lanes_count)) continue;
        if (reachable(w.x[i], w.y[i], cand) && moving && mobil(w, i, cand)) w.target[i] = cand;
      }
    }
    for (int i = 1; i < n; ++i) {
      if (!w.present[i] || w.crashed[i]) continue;
      T a = idm[i];
      if (w.lane[i] != w.target[i]) {  // also brake for the target lane's front vehicle
        int tf, tr;
        neighbours(w, i, int(w.target[i]), tf, tr);
        a = std::min(a, free[i] - interaction(w, i, tf));
      }
      w.acc[i] = clamp(a, -T(p.acc_max), T(p.acc_max));
      w.steer[i] = steer(w, i);
    }
    w.steer[0] = steer(w, 0);
    w.acc[0] = (w.vt[0] - w.v[0]) * T(p.kp_a);
  }

  int closest_lane(T x, T y, T h) const {
    T past_end = std::max(x - T(p.lane_length), T(0)), before = std::max(T(0) - x, T(0));
    T angle = std::fabs(wrap_to_pi(h - T(0)));
    int best = 0;
    T best_d = 0;
    for (int l = 0; l < int(lane_y.size()); ++l) {
      T d = ((std::fabs(y - lane_y[l]) + past_end) + before) + angle;
      if (l == 0 || d < best_d) best = l, best_d = d;
    }
    return best;
  }

  void move(World<T>& w) const {  // Vehicle.step(dt) of every row, padding included
    move_rows(w, T(p.dt), T(p.max_speed), T(p.min_speed), T(p.length / 2),
              [this](T x, T y, T h, int64_t) { return closest_lane(x, y, h); });
  }
};

template <class T>
void step_rows(const Params& p, const Table& t, int64_t lo, int64_t hi, int n, int frames,
               void* obs) {
  Model<T> model(p, n);
  const int64_t size = int64_t(p.obs_count) * int64_t(p.obs_features);
  for (int64_t b = lo; b < hi; ++b) {
    World<T> w = rows_of<T>(t, b, n);
    for (int64_t f = 0; f < frames; ++f) {
      if ((t.steps[b] + f) % frames == 0) model.meta_action(w, t.action[b], t.speed_index[b]);
      model.act(w);
      model.move(w);
      collide(p, w);
    }
    if (frames) t.steps[b] += frames;
    if (obs) observe(p, w, static_cast<T*>(obs) + b * size, model.key, model.order);
  }
}

template <class T>
void reset_rows(const Params& p, const Table& t, int64_t batch, int n, const bool* rows,
                const int64_t* key, int64_t* counter, double* time, int64_t* words,
                int64_t* seeds) {
  for (int64_t b = 0; b < batch; ++b) {
    if (!rows[b]) continue;
    World<T> w = rows_of<T>(t, b, n);
    fresh_world(p, w, key[b], counter[b], words + b * 10);
    time[b] = 0, t.steps[b] = 0, t.speed_index[b] = int64_t(p.ego_index), seeds[b] = -1;
  }
}

}  // namespace highway

using highway::Params;
using highway::Table;

// Steps B worlds by `frames` substeps (0: observes only), then writes each world's
// observation into `obs` ([B, obs_count, obs_features], or null for none).
extern "C" int highway_step(const Params* p, const Table* t, int64_t batch, int64_t n,
                            int frames, void* obs, int is_double, int threads) {
  if (p->n_speeds < 1 || p->n_speeds > 16 || p->obs_features > 8 || n < 1) return 1;
  highway::for_blocks(batch, threads, [&](int64_t lo, int64_t hi) {
    if (is_double)
      highway::step_rows<double>(*p, *t, lo, hi, int(n), frames, obs);
    else
      highway::step_rows<float>(*p, *t, lo, hi, int(n), frames, obs);
  });
  return 0;
}

// Fresh episodes in the rows of `rows` ([B] bool): the vehicle table, speed index, time,
// steps, stream counters, highway-env generator words ([B, 10]) and seeds (-1).
extern "C" int highway_reset(const Params* p, const Table* t, int64_t batch, int64_t n,
                             const bool* rows, const int64_t* key, int64_t* counter,
                             double* time, int64_t* words, int64_t* seeds, int is_double) {
  if (n < 1) return 1;
  if (is_double)
    highway::reset_rows<double>(*p, *t, batch, int(n), rows, key, counter, time, words, seeds);
  else
    highway::reset_rows<float>(*p, *t, batch, int(n), rows, key, counter, time, words, seeds);
  return 0;
}
