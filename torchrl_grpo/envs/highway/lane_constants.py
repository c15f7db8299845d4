"""A highway-env road network's lanes as a :class:`~torchrl_grpo.sim.lanes.LaneGeometry`.

The constants are read (float64) from highway-env's own lane objects, never retyped,
in the network's flat order (the order ``get_closest_lane_index`` scans), together
with the graph facts the simulator needs: each lane's id within its road, its left
and right neighbours (``clip(id -/+ 1)`` on the same road, as ``MDPVehicle`` moves
its target), its side lanes (``network.side_lanes``) and the lane that
``network.next_lane`` hands a route-less vehicle over to at its end.

Example:
    >>> import gymnasium as gym
    >>> env = gym.make("merge-v0")
    >>> _ = env.reset(seed=0)
    >>> graph = road_graph(env.unwrapped.road.network)
    >>> graph.keys[4], graph.geometry.forbidden[4], graph.next_lane[8]
    (('b', 'c', 2), True, 4)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from highway_env.road.lane import CircularLane, SineLane, StraightLane
from highway_env.road.road import RoadNetwork

from torchrl_grpo.sim.lanes import LaneGeometry

__all__ = ["RoadGraph", "lane_keys", "road_graph"]


@dataclass(frozen=True)
class RoadGraph:
    """A road network's lanes in flat order, their geometry and their graph links.

    Attributes:
        keys: the lane indices ``(from, to, id)`` in flat order.
        geometry: the lanes' constants.
        lane_id: each lane's id within its road.
        left: the flat lane ``(from, to, clip(id - 1))``.
        right: the flat lane ``(from, to, clip(id + 1))``.
        next_lane: the flat lane ``next_lane`` hands over to without a route (itself
            where no road leaves the lane's end).
        speed_limit: each lane's speed limit (m/s).

    Example:
        >>> from highway_env.road.road import RoadNetwork
        >>> road_graph(RoadNetwork.straight_road_network(2)).lane_id
        (0, 1)
    """

    keys: tuple[tuple[str, str, int], ...]
    geometry: LaneGeometry
    lane_id: tuple[int, ...]
    left: tuple[int, ...]
    right: tuple[int, ...]
    next_lane: tuple[int, ...]
    speed_limit: tuple[float, ...]


def lane_keys(network: RoadNetwork) -> list[tuple[str, str, int]]:
    """The network's lane indices in the order ``get_closest_lane_index`` scans them.

    Example:
        >>> from highway_env.road.road import RoadNetwork
        >>> lane_keys(RoadNetwork.straight_road_network(2))
        [('0', '1', 0), ('0', '1', 1)]
    """
    return [
        (_from, _to, _id)
        for _from, to_dict in network.graph.items()
        for _to, lanes in to_dict.items()
        for _id in range(len(lanes))
    ]


def _constants(lane) -> dict:
    base = {
        "kind": 0, "start_x": 0.0, "start_y": 0.0, "dir_x": 1.0, "dir_y": 0.0, "lat_x": -0.0,
        "lat_y": 1.0, "heading": 0.0, "length": float(lane.length), "width": float(lane.width),
        "amplitude": 0.0, "pulsation": 0.0, "phase": 0.0, "center_x": 0.0, "center_y": 0.0,
        "radius": 1.0, "start_phase": 0.0, "turn": 1.0, "forbidden": bool(lane.forbidden),
    }  # fmt: skip
    if isinstance(lane, StraightLane):  # SineLane included
        base |= {
            "start_x": float(lane.start[0]), "start_y": float(lane.start[1]),
            "dir_x": float(lane.direction[0]), "dir_y": float(lane.direction[1]),
            "lat_x": float(lane.direction_lateral[0]), "lat_y": float(lane.direction_lateral[1]),
            "heading": float(lane.heading),
        }  # fmt: skip
        if isinstance(lane, SineLane):
            base |= {
                "amplitude": float(lane.amplitude),
                "pulsation": float(lane.pulsation),
                "phase": float(lane.phase),
            }
    elif isinstance(lane, CircularLane):
        base |= {
            "kind": 1, "center_x": float(lane.center[0]), "center_y": float(lane.center[1]),
            "radius": float(lane.radius), "start_phase": float(lane.start_phase),
            "turn": float(lane.direction),
        }  # fmt: skip
    else:
        raise ValueError(f"the tensor simulator has no geometry for {type(lane).__name__}")
    return base


def road_graph(network: RoadNetwork) -> RoadGraph:
    """Read a network's lanes, in flat order, with their links.

    Raises:
        ValueError: a lane of a type the simulator does not model.

    Example:
        >>> from highway_env.road.road import RoadNetwork
        >>> graph = road_graph(RoadNetwork.straight_road_network(3))
        >>> graph.left, graph.right, graph.next_lane
        ((0, 0, 1), (1, 2, 2), (0, 1, 2))
    """
    keys = lane_keys(network)
    flat = {key: k for k, key in enumerate(keys)}
    lanes = [network.get_lane(key) for key in keys]
    left, right, following = [], [], []
    for _from, _to, _id in keys:
        count = len(network.graph[_from][_to])
        left.append(flat[(_from, _to, int(np.clip(_id - 1, 0, count - 1)))])
        right.append(flat[(_from, _to, int(np.clip(_id + 1, 0, count - 1)))])
        lane = network.get_lane((_from, _to, _id))
        # The hand-over at the lane's end, as follow_road asks for it (no route); the
        # projected position is the lane's end, where after_end first holds.
        end = lane.position(lane.length, 0)
        try:
            nxt = network.next_lane((_from, _to, _id), route=None, position=end)
        except KeyError:
            nxt = (_from, _to, _id)
        following.append(flat[nxt])
    return RoadGraph(
        keys=tuple(keys),
        geometry=LaneGeometry.of([_constants(lane) for lane in lanes]),
        lane_id=tuple(int(k[2]) for k in keys),
        left=tuple(left),
        right=tuple(right),
        next_lane=tuple(following),
        speed_limit=tuple(float(lane.speed_limit) for lane in lanes),
    )
