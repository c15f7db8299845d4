// The substeps of B merge-v0 or roundabout-v0 worlds in C++: the frames of
// torchrl_grpo/sim/merge.py and roundabout.py (the ego's and the IDM vehicles' act() on
// the road graph, kinematics, every pair's collision, merge's obstacle; routed_model.h),
// and intersection-v0's frames, which add the right of way (intersection_rules.h).
//
// A loop per world and per vehicle, in road order: each IDM vehicle follows the road
// (its route, on the roundabout), runs MOBIL (with the route rule while a route's head
// leg names a lane), scans for aborts (reading the targets decided before it and the
// old ones after it, as the tensor path's scan does), steers and brakes; then every
// vehicle moves and takes its closest lane; then pairs collide. Each expression
// keeps the tensor path's operation order and rounds its constants to T as it does
// (a Python float over a tensor, `c / t`, is torch's reciprocal(t) * c), so float64
// agrees with the tensor path to rounding. Worlds are split over `threads` threads.
//
// Built and loaded by torchrl_grpo/sim/routed_native.py (intersection_native.py calls
// intersection_frames).
#include "intersection_rules.h"
#include "routed_model.h"

namespace highway {

template <class T>
void step_worlds(const RoutedParams& p, const Table& t, const int64_t* legs, int64_t* heads,
                 int64_t lo, int64_t hi, int n, int frames) {
  RoutedModel<T> model(p, n);
  for (int64_t b = lo; b < hi; ++b) {
    World<T> w = rows_of<T>(t, b, n);
    Routes<T> routes{p, model.lanes, legs ? legs + b * n * p.route_length : nullptr,
                     heads ? heads + b * n : nullptr};
    for (int f = 0; f < frames; ++f) {
      const bool first = (t.steps[b] + f) % int64_t(p.frames) == 0;
      model.substep(w, routes, t.action[b], first, t.speed_index[b]);
    }
    t.steps[b] += frames;
  }
}

template <class T>
void intersection_worlds(const RoutedParams& p, const RulesParams& q, const Table& t,
                         const int64_t* legs, int64_t* heads, int8_t* yielding,
                         int64_t* road_steps, const int64_t* ego_rank, int64_t lo, int64_t hi,
                         int n, int frames) {
  IntersectionModel<T> model(p, q, n);
  for (int64_t b = lo; b < hi; ++b) {
    World<T> w = rows_of<T>(t, b, n);
    Routes<T> routes{p, model.lanes, legs + b * n * p.route_length, heads + b * n};
    // Only the rows up to the last present one: a free row changes no present one's
    // result, and a spawn writes all of a row (the tensor path narrows its table too).
    int used = 1;
    for (int k = 1; k < n; ++k)
      if (w.present[k]) used = k + 1;
    w.n = used;
    model.use_rows(used, ego_rank[b]);
    for (int f = 0; f < frames; ++f) {
      const bool first = (t.steps[b] + f) % int64_t(p.frames) == 0;
      model.substep(w, routes, t.action[b], first, t.speed_index[b], road_steps[b],
                    yielding + b * n);
    }
    t.steps[b] += frames;
  }
}

}  // namespace highway

// Steps B worlds of n vehicles by `frames` substeps, in place: the vehicle table, the
// speed indices and steps of `t`, and the route heads ([B, n]); legs are [B, n, R]
// (both null on a road without routes).
extern "C" int routed_step(const highway::RoutedParams* p, const highway::Table* t,
                           const int64_t* legs, int64_t* heads, int64_t batch, int64_t n,
                           int frames, int is_double, int threads) {
  if (p->n_speeds < 1 || p->n_speeds > 16 || n < 1 || p->frames < 1) return 1;
  highway::for_blocks(batch, threads, [&](int64_t lo, int64_t hi) {
    if (is_double)
      highway::step_worlds<double>(*p, *t, legs, heads, lo, hi, int(n), frames);
    else
      highway::step_worlds<float>(*p, *t, legs, heads, lo, hi, int(n), frames);
  });
  return 0;
}

// Steps B intersection-v0 worlds of n vehicles by `frames` substeps, in place: the vehicle
// table, speed indices and steps of `t`, the route heads and yield states ([B, n]) and
// the road frames ([B]); legs are [B, n, R], ego_rank [B] (the ego's place in road order).
extern "C" int intersection_frames(const highway::RoutedParams* p, const highway::RulesParams* q,
                                   const highway::Table* t, const int64_t* legs, int64_t* heads,
                                   int8_t* yielding, int64_t* road_steps, const int64_t* ego_rank,
                                   int64_t batch, int64_t n, int frames, int is_double,
                                   int threads) {
  if (p->n_speeds < 1 || p->n_speeds > 16 || n < 1 || p->frames < 1 || q->every < 1 ||
      q->n_times < 0 || q->n_times > 16 || p->route_length < 1)
    return 1;
  for (int64_t b = 0; b < batch; ++b)
    if (ego_rank[b] < 0 || ego_rank[b] >= n) return 2;
  highway::for_blocks(batch, threads, [&](int64_t lo, int64_t hi) {
    if (is_double)
      highway::intersection_worlds<double>(*p, *q, *t, legs, heads, yielding, road_steps,
                                           ego_rank, lo, hi, int(n), frames);
    else
      highway::intersection_worlds<float>(*p, *q, *t, legs, heads, yielding, road_steps,
                                          ego_rank, lo, hi, int(n), frames);
  });
  return 0;
}
