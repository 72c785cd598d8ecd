"""Write an episode as ASAM OpenSCENARIO 1.x (``.xosc``) with its road as OpenDRIVE
(``.xodr``), through ``scenariogeneration`` (the ``export`` extra). Used by ``adv3d export``.

* Road: one OpenDRIVE road per lane (road id = lane id), its reference line the lane's centre
  line as straight segments (``line`` geometries placed at the centre-line vertices), one
  right-hand driving lane whose width follows the lane's (linear per segment) and a lane offset of
  half that width, so the driving lane is centred on the centre line. Roads are not linked
  (no junctions): positions are world coordinates, so a replay needs no road topology.
* Entities: ``ego`` and ``actor<ID>``, vehicles with their bounding box (length, width, height;
  the reference point is the footprint centre on the ground, not the rear axle, so the box is
  centred on it and the axles sit at +-wheelbase/2), category from the class, and a
  ``model3d`` file where given (the found shape's glb).
* Storyboard: every vehicle follows its trajectory (a polyline of world positions with absolute
  times, ``FollowTrajectoryAction`` in ``position`` mode, time reference absolute), the ego its
  driven (closed-loop) one; a vehicle that enters or leaves during the episode is hidden
  (``VisibilityAction``) before its first and after its last frame. The story stops at T dt.

A tool that drives its own ego replaces the ego's trajectory action with its controller and keeps
the Init (its initial pose and speed).
"""
from __future__ import annotations

import datetime
from pathlib import Path

import numpy as np

from .commonroad_export import Vehicle
from .schema import Lane

#: OpenSCENARIO vehicle category of each adv3d class (anything else: car)
CATEGORIES = {"truck": "truck", "garbage_truck": "truck", "fire_truck": "truck", "bus": "bus",
              "motorcycle": "motorbike", "van": "van"}
#: fixed creation date, so the same episode gives the same bytes
CREATED = datetime.datetime(2000, 1, 1)


def entity_name(vehicle_id: int | None) -> str:
    """``ego`` for None, else ``actor<ID>``."""
    return "ego" if vehicle_id is None else f"actor{int(vehicle_id)}"


def write_opendrive(path: str | Path, lanes: list[Lane], name: str) -> None:
    """The lanes as an OpenDRIVE 1.5 road network at ``path`` (see the module docstring)."""
    from scenariogeneration import xodr

    odr = xodr.OpenDrive(name)
    for lane in lanes:
        c = np.asarray(lane.centerline, dtype=np.float64)
        w = np.broadcast_to(np.asarray(lane.width, dtype=np.float64), (len(c),))
        seg = np.diff(c, axis=0)
        length = np.hypot(seg[:, 0], seg[:, 1])
        keep = length > 1e-6
        starts, heads, lens = c[:-1][keep], np.arctan2(seg[keep, 1], seg[keep, 0]), length[keep]
        w0, w1 = w[:-1][keep], w[1:][keep]
        plan = xodr.PlanView()
        lanes_el = xodr.Lanes()
        s = 0.0
        for (x, y), h, L, a, b in zip(starts, heads, lens, w0, w1):
            plan.add_fixed_geometry(xodr.Line(float(L)), float(x), float(y), float(h), s=s)
            slope = float((b - a) / L)
            centre = xodr.Lane(a=0.0)
            centre.add_roadmark(xodr.RoadMark(xodr.RoadMarkType.none))
            section = xodr.LaneSection(s, centre)
            driving = xodr.Lane(lane_type=xodr.LaneType.driving, a=float(a), b=slope)
            driving.add_roadmark(xodr.RoadMark(xodr.RoadMarkType.solid))
            section.add_right_lane(driving)
            lanes_el.add_lanesection(section)
            lanes_el.add_laneoffset(xodr.LaneOffset(s=s, a=float(a) / 2, b=slope / 2))
            s += float(L)
        road = xodr.Road(int(lane.id), plan, lanes_el, name=f"lane{lane.id}")
        road.add_elevation(0.0, 0.0, 0.0, 0.0, 0.0)  # flat (the schema wants one elevation record)
        odr.add_road(road)
    odr.write_xml(str(path))


def write_openscenario(path: str | Path, ego: Vehicle, actors: list[Vehicle], dt: float, *, name: str, author: str,
                       description: str, wheelbase: float, road_file: str | None = None,
                       models: dict[int, str] | None = None) -> None:
    """The episode as OpenSCENARIO 1.2 at ``path`` (see the module docstring). ``models``:
    actor id -> model3d file (relative to the .xosc); ``road_file``: the OpenDRIVE file,
    relative to the .xosc, or None."""
    from scenariogeneration import xosc

    models = models or {}
    T = len(ego.poses)
    entities = xosc.Entities()
    init = xosc.Init()
    story = xosc.Story("replay")
    act = xosc.Act("episode", xosc.ValueTrigger("start", 0, xosc.ConditionEdge.none,
                                                xosc.SimulationTimeCondition(0, xosc.Rule.greaterThan)))

    def at(t: float, tag: str):
        return xosc.ValueTrigger(tag, 0, xosc.ConditionEdge.rising, xosc.SimulationTimeCondition(float(t), xosc.Rule.greaterThan))

    for vid, vehicle in [(None, ego), *[(a.obstacle_id, a) for a in actors]]:
        poses = np.asarray(vehicle.poses, dtype=np.float64)
        speeds = np.asarray(vehicle.speeds, dtype=np.float64)
        ok = np.flatnonzero(np.isfinite(poses[:, 0]))
        if not len(ok):
            continue
        ename = entity_name(vid)
        L, W, H = (float(d) for d in vehicle.dimensions)
        wb = wheelbase if vid is None else min(wheelbase, 0.6 * L)
        axle = dict(maxsteer=0.6, wheeldia=0.7, track_width=0.85 * W, zpos=0.35)
        category = getattr(xosc.VehicleCategory, CATEGORIES.get(vehicle.cls, "car"))
        entities.add_scenario_object(ename, xosc.Vehicle(
            ename, category, xosc.BoundingBox(W, L, H, 0.0, 0.0, H / 2),
            xosc.Axle(xpos=wb / 2, **axle), xosc.Axle(xpos=-wb / 2, **axle),
            max_speed=70.0, max_acceleration=10.0, max_deceleration=10.0,
            model3d=models.get(vid) if vid is not None else None))
        a, b = int(ok[0]), int(ok[-1]) + 1
        first = poses[a]
        init.add_init_action(ename, xosc.TeleportAction(xosc.WorldPosition(float(first[0]), float(first[1]), 0.0,
                                                                           float(first[2]))))
        init.add_init_action(ename, xosc.AbsoluteSpeedAction(float(speeds[a]), xosc.TransitionDynamics(
            xosc.DynamicsShapes.step, xosc.DynamicsDimension.time, 0.0)))
        maneuver = xosc.Maneuver(f"{ename}_drive")
        event = xosc.Event(f"{ename}_trajectory", xosc.Priority.override)
        frames = [f for f in range(a, b) if np.isfinite(poses[f, 0])]
        trajectory = xosc.Trajectory(f"{ename}_trajectory", False)
        trajectory.add_shape(xosc.Polyline([f * dt for f in frames],
                                           [xosc.WorldPosition(float(poses[f, 0]), float(poses[f, 1]), 0.0,
                                                               float(poses[f, 2])) for f in frames]))
        event.add_action("follow", xosc.FollowTrajectoryAction(
            trajectory, xosc.FollowingMode.position, xosc.ReferenceContext.absolute, 1.0, 0.0))
        event.add_trigger(at(-1.0, f"{ename}_start"))
        maneuver.add_event(event)
        if a > 0 or b < T:  # enters or leaves during the episode: hidden outside its frames
            hide = xosc.VisibilityAction(False, False, False)
            if a > 0:
                init.add_init_action(ename, hide)
                show = xosc.Event(f"{ename}_appears", xosc.Priority.parallel)
                show.add_action("show", xosc.VisibilityAction(True, True, True))
                show.add_trigger(at((a - 0.5) * dt, f"{ename}_enters"))
                maneuver.add_event(show)
            if b < T:
                gone = xosc.Event(f"{ename}_leaves", xosc.Priority.parallel)
                gone.add_action("hide", hide)
                gone.add_trigger(at((b - 0.5) * dt, f"{ename}_left"))
                maneuver.add_event(gone)
        group = xosc.ManeuverGroup(f"{ename}_group")
        group.add_actor(ename)
        group.add_maneuver(maneuver)
        act.add_maneuver_group(group)
    story.add_act(act)
    stop = xosc.ValueTrigger("end", 0, xosc.ConditionEdge.rising,
                             xosc.SimulationTimeCondition(float(T * dt), xosc.Rule.greaterThan), "stop")
    board = xosc.StoryBoard(init, stop)
    board.add_story(story)
    scenario = xosc.Scenario(name, author, xosc.ParameterDeclarations(), entities, board,
                             xosc.RoadNetwork(roadfile=road_file), xosc.Catalog(), osc_minor_version=2,
                             creation_date=CREATED, header_properties=None)
    scenario.header.description = description
    scenario.write_xml(str(path))
