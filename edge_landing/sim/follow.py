"""``edge-run --camera sim-follow[:STYLE[:SEED]][@URL]``: a synthetic camera that flies with the autopilot.

The camera renders the procedural world from the vehicle pose the autopilot reports over MAVLink
(LOCAL_POSITION_NED + ATTITUDE, or the simulator's SIM_STATE when it is streamed together with
GPS_GLOBAL_ORIGIN), and stamps each frame with that pose's time on this computer's monotonic clock
(docs/ARCHITECTURE.md §3). The autopilot's local NED origin (its home) is placed on a large open, flat patch
of the world, found by vertical ray casting and deterministic per world seed, so that the world point is
``home_offset_ned_m + autopilot NED``. Optionally a downward DISTANCE_SENSOR (orientation 25, cm) ray cast in
the world is sent back, for autopilots configured with a MAVLink rangefinder, so that their height above
ground matches the world.

The pose comes over a MAVLink connection of its own (default ``udpin:127.0.0.1:14562``): the camera is the
simulator's, not the drone's, so it does not share the runtime's telemetry. Example::

    edge-run --camera sim-follow:urban:3@udpin:127.0.0.1:14562 --mav udpin:127.0.0.1:14561
"""
from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Any, Optional, Protocol, Tuple

import numpy as np

from edge_landing.runtime.core.camera import Attitude, Intrinsics, Mount
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.messages import VehicleState
from edge_landing.runtime.io.sources import Reader, SourceConfig, sim_style_seed

from .effects import Effects, sample_effects
from .render import Renderer
from .world import MISS, Style, World, build_world

log = logging.getLogger(__name__)
DEFAULT_POSE_URL = "udpin:127.0.0.1:14562"
# 640×480, as edge-run's scripted sim camera: motion geometry (ARCHITECTURE.md §11) needs the camera's own
# pixels to confirm a spot (at 160×120 a DIS patch covers > 1.5 m of ground beyond ~15 m: nothing was ever
# confirmed in the closed loop). Renders in ~0.2 s on one busy core, so the loop runs at ~4-5 frames/s.
DEFAULT_SIZE = (640, 480)
HOME_SEARCH_HALF_M = 200.0         # flights stay well inside the 1.2 km world
HOME_CLEAR_RADIUS_M = (15.0, 10.0, 6.0)
POSE_TIMEOUT_S = 2.0
RANGEFINDER_MAX_M = 200.0
EARTH_RADIUS_M = 6378137.0


@dataclass(frozen=True)
class PoseSample:
    """A vehicle pose: ``time_s`` on the local monotonic clock, NED position in the autopilot's local frame."""

    time_s: float
    position_ned_m: np.ndarray
    attitude: Attitude
    source: str


class PoseProvider(Protocol):
    def latest(self) -> Optional[PoseSample]: ...

    def send_rangefinder(self, distance_m: float) -> None: ...

    def close(self) -> None: ...


# -- where the autopilot's home lies in the world ---------------------------------------------------------
def open_ground(world: World, north: np.ndarray, east: np.ndarray, max_tilt_deg: float = 5.0) -> np.ndarray:
    """True where the first surface straight below is bare terrain (nothing standing on it) and level."""
    o = np.stack([north, east, np.full(north.shape, -1000.0)], axis=-1)
    t, prim = world.intersect(o, np.broadcast_to(np.array([0.0, 0.0, 1.0]), o.shape))
    bare = (prim != MISS) & (np.abs(-1000.0 + np.nan_to_num(t) - world.terrain.z_at(north, east)) < 0.05)
    tilt = np.degrees(np.arccos(np.clip(np.abs(world.normals[np.maximum(prim, 0), 2]), 0.0, 1.0)))
    ok: np.ndarray = bare & (tilt <= max_tilt_deg)
    return ok


def _disc(radius_m: float, step_m: float = 1.0) -> np.ndarray:
    g = np.arange(-radius_m, radius_m + 1e-9, step_m)
    n, e = np.meshgrid(g, g, indexing="ij")
    keep = n ** 2 + e ** 2 <= radius_m ** 2
    return np.stack([n[keep], e[keep]], axis=-1)


def place_home(world: World) -> np.ndarray:
    """World NED (m) of the autopilot's home: the centre of an open, level disc (15 m radius if one exists).

    Candidates are the generator's open landing spots and a coarse grid near the world's centre, tried in an
    order drawn from the world's seed, so the same world always gives the same home.
    """
    rng = np.random.default_rng([world.seed, 0xF011])
    g = np.arange(-HOME_SEARCH_HALF_M, HOME_SEARCH_HALF_M + 1, 20.0)
    grid = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    spots = world.landing_spots.reshape(-1, 2)
    cands = np.concatenate([spots[np.abs(spots).max(axis=1) < HOME_SEARCH_HALF_M], grid])
    cands = cands[rng.permutation(len(cands))]
    for radius in HOME_CLEAR_RADIUS_M:
        disc = _disc(radius)
        for n, e in cands:
            pts = disc + (n, e)
            if open_ground(world, pts[:, 0], pts[:, 1]).all():
                z = float(world.terrain.z_at(np.array([n]), np.array([e]))[0])
                return np.array([float(n), float(e), z])
    raise InputError(f"the {world.style.value} world of seed {world.seed} has no open, level patch of "
                     f"{HOME_CLEAR_RADIUS_M[-1]:.0f} m radius near its centre for the autopilot's home")


def height_above_ground_m(world: World, position_world_ned_m: np.ndarray) -> float:
    """Vertical distance from a world point down to the first surface below it (a down rangefinder)."""
    n, e, d = (float(v) for v in position_world_ned_m)
    t, prim = world.intersect(np.array([[n, e, d]]), np.array([[0.0, 0.0, 1.0]]))
    if prim[0] == MISS:
        return float(world.terrain.z_at(np.array([n]), np.array([e]))[0] - d)
    return float(t[0])


# -- the pose over MAVLink --------------------------------------------------------------------------------
class MavlinkPoseProvider:
    """Keeps the newest vehicle pose from an autopilot's MAVLink stream, in a thread of its own.

    Autopilot times (``time_boot_ms``) are mapped to the local clock with the smallest observed offset
    (the sample that travelled fastest). The position is extrapolated with the reported velocity to the
    attitude's time, so one pose has one time. SIM_STATE, when present with GPS_GLOBAL_ORIGIN, wins: it is
    the simulator's truth, not the autopilot's estimate.
    """

    def __init__(self, url: str, heartbeat_period_s: float = 1.0):
        from edge_landing.runtime.io.mavlink_link import check_url, load_mavutil

        check_url(url)
        self._mavutil: Any = load_mavutil()
        m = self._mavutil.mavlink
        self._conn = self._mavutil.mavlink_connection(url, source_system=1, source_component=m.MAV_COMP_ID_CAMERA)
        self.url = url
        self._heartbeat_period_s = heartbeat_period_s
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._offset_s: Optional[float] = None
        self._attitude: Optional[Tuple[float, Attitude]] = None         # (remote_s, Attitude)
        self._position: Optional[Tuple[float, np.ndarray, np.ndarray]] = None         # (remote_s, ned, velocity)
        self._origin: Optional[Tuple[float, float, float]] = None           # (lat_rad, lon_rad, alt_m) of the local NED origin
        self._sim: Optional[PoseSample] = None
        self.peer: Optional[Tuple[int, int]] = None
        self._thread = threading.Thread(target=self._run, name="sim-follow-pose", daemon=True)
        self._thread.start()

    def latest(self) -> Optional[PoseSample]:
        with self._lock:
            if self._sim is not None:
                return self._sim
            if self._attitude is None or self._position is None or self._offset_s is None:
                return None
            t_att, att = self._attitude
            t_pos, ned, vel = self._position
            ned = ned + vel * float(np.clip(t_att - t_pos, -0.2, 0.2))
            return PoseSample(t_att + self._offset_s, ned, att, "LOCAL_POSITION_NED+ATTITUDE")

    def send_rangefinder(self, distance_m: float) -> None:
        """DISTANCE_SENSOR, orientation 25 (down), centimetres; dropped silently when nobody listens."""
        if self.peer is None:
            return
        m = self._mavutil.mavlink
        cm = int(round(min(max(distance_m, 0.0), RANGEFINDER_MAX_M) * 100))
        msg = m.MAVLink_distance_sensor_message(int(time.monotonic() * 1000) & 0xFFFFFFFF, 10,
                                                int(RANGEFINDER_MAX_M * 100), cm, m.MAV_DISTANCE_SENSOR_LASER,
                                                1, 25, 0)
        self._send(msg)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._conn.close()

    def _send(self, msg: Any) -> None:
        try:
            self._conn.mav.send(msg)
        except OSError:
            pass  # nobody listening yet: the next frame tries again

    def _local(self, remote_s: float) -> None:
        offset = time.monotonic() - remote_s
        if self._offset_s is None or offset < self._offset_s or offset > self._offset_s + 2.0:
            self._offset_s = offset  # the fastest sample, or a restarted autopilot clock

    def _run(self) -> None:
        m = self._mavutil.mavlink
        next_hb = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_hb:
                self._send(m.MAVLink_heartbeat_message(m.MAV_TYPE_CAMERA, m.MAV_AUTOPILOT_INVALID, 0, 0,
                                                       m.MAV_STATE_ACTIVE, 3))
                next_hb = now + self._heartbeat_period_s
            try:
                msg = self._conn.recv_match(blocking=True, timeout=0.05)
            except OSError:
                self._stop.wait(0.2)
                continue
            if msg is not None:
                self._handle(msg)

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        with self._lock:
            if kind == "HEARTBEAT" and msg.autopilot != self._mavutil.mavlink.MAV_AUTOPILOT_INVALID:
                self.peer = self.peer or (msg.get_srcSystem(), msg.get_srcComponent())
            elif kind == "ATTITUDE":
                self._local(msg.time_boot_ms / 1000.0)
                self._attitude = (msg.time_boot_ms / 1000.0, Attitude(msg.roll, msg.pitch, msg.yaw))
            elif kind == "LOCAL_POSITION_NED":
                self._local(msg.time_boot_ms / 1000.0)
                self._position = (msg.time_boot_ms / 1000.0, np.array([msg.x, msg.y, msg.z]),
                                  np.array([msg.vx, msg.vy, msg.vz]))
            elif kind == "GPS_GLOBAL_ORIGIN":
                self._origin = (math.radians(msg.latitude * 1e-7), math.radians(msg.longitude * 1e-7),
                                msg.altitude / 1000.0)
            elif kind == "SIM_STATE" and self._origin is not None:
                self._sim = sim_state_pose(msg, self._origin)



def sim_state_pose(msg: Any, origin: Tuple[float, float, float]) -> PoseSample:
    """SIM_STATE (degrees as float, or degE7 in the MAVLink 2 extension) to local NED about ``origin``
    (latitude, longitude in radians, altitude in metres), flat earth: exact enough within a few km."""
    lat0, lon0, alt0 = origin
    lat = getattr(msg, "lat_int", 0) * 1e-7 or msg.lat
    lon = getattr(msg, "lon_int", 0) * 1e-7 or msg.lon
    north = (math.radians(lat) - lat0) * EARTH_RADIUS_M
    east = (math.radians(lon) - lon0) * EARTH_RADIUS_M * math.cos(lat0)
    ned = np.array([north, east, -(msg.alt - alt0)])
    return PoseSample(time.monotonic(), ned, Attitude(msg.roll, msg.pitch, msg.yaw), "SIM_STATE")


# -- the reader -------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FollowSpec:
    style: Style = Style.SUBURBAN
    seed: int = 0
    pose_url: str = DEFAULT_POSE_URL
    gimbal: bool = False        # the camera is stabilised: the mount's pitch below the horizon, yaw with the heading

    @staticmethod
    def parse(camera: str) -> FollowSpec:
        """``sim-follow[:STYLE[:SEED]][:gimbal][@URL]``."""
        head, _, url = camera.partition("@")
        style, seed = sim_style_seed(camera)
        return FollowSpec(Style.from_string(style), seed, url or DEFAULT_POSE_URL, "gimbal" in head.split(":")[1:])


class FollowReader(Reader):
    """Renders the world from the newest autopilot pose at ``fps`` (default 10).

    ``capture_time_s`` is the pose's local time, which the grabber uses as the frame's capture time, so
    the runtime matches the same pose from its own telemetry (the autopilot link); ``last_state`` is that
    pose with the ray-cast height above ground, the frame's own telemetry when edge-run has no link. A pose
    older than ``POSE_TIMEOUT_S`` is a camera fault (OSError: the grabber reopens the camera with back-off).
    """

    def __init__(self, config: SourceConfig, provider: Optional[PoseProvider] = None, rangefinder: bool = True):
        spec = FollowSpec.parse(config.camera)
        width, height = (config.width, config.height) if config.width and config.height else DEFAULT_SIZE
        self.world = build_world(spec.style, spec.seed)
        self.home_world_ned_m = place_home(self.world)
        self.intrinsics = Intrinsics.from_hfov(width, height)
        self.mount = Mount()
        self.renderer = Renderer(self.world, self.intrinsics, self.mount)
        self.effects: Effects = sample_effects(np.random.default_rng([spec.seed, 0xF011, 2]))
        self._noise = np.random.default_rng([spec.seed, 0xF011, 3])
        self.period_s = 1.0 / (config.fps or 10.0)
        self.provider: PoseProvider = provider or MavlinkPoseProvider(spec.pose_url)
        self.rangefinder = rangefinder
        self.gimbal = spec.gimbal
        self.name = f"sim-follow:{spec.style.value}:{spec.seed}{':gimbal' if spec.gimbal else ''}@{spec.pose_url}"
        self.capture_time_s: Optional[float] = None
        self.last_pose: Optional[PoseSample] = None
        self._next_s = time.monotonic()
        log.info("sim-follow: %s world seed %d, autopilot home at world NED %s, pose from %s", spec.style.value,
                 spec.seed, np.round(self.home_world_ned_m, 1).tolist(), spec.pose_url)

    def read(self) -> Optional[np.ndarray]:
        delay = self._next_s - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        self._next_s = max(self._next_s + self.period_s, time.monotonic())
        pose = self._wait_for_pose()
        world_ned = self.home_world_ned_m + pose.position_ned_m
        # On a gimbal the camera keeps its pitch to the horizon while the vehicle tilts: as a fixed mount on a
        # level vehicle with the same heading.
        att = Attitude(0.0, 0.0, pose.attitude.yaw_rad) if self.gimbal else pose.attitude
        rgb = self.renderer.render(world_ned, att, self.effects, self._noise).rgb
        agl_m = height_above_ground_m(self.world, world_ned)
        if self.rangefinder:
            self.provider.send_rangefinder(agl_m)
        self.capture_time_s, self.last_pose = pose.time_s, pose
        # The frame's own pose, for edge-run without --mav (with an autopilot link edge-run uses the link's
        # telemetry instead, as on the drone): the pose it was rendered from and the ray-cast height.
        self.last_state = VehicleState(pose.time_s, pose.attitude, pose.position_ned_m.copy(), agl_m,
                                       f"sim-follow ray cast ({pose.source})")
        return rgb

    def _wait_for_pose(self) -> PoseSample:
        deadline = time.monotonic() + POSE_TIMEOUT_S
        while True:
            pose = self.provider.latest()
            fresh = pose is not None and time.monotonic() - pose.time_s < POSE_TIMEOUT_S
            if fresh and (self.capture_time_s is None or pose.time_s > self.capture_time_s):  # type: ignore[union-attr]
                return pose  # type: ignore[return-value]
            if time.monotonic() > deadline:
                raise OSError(f"{self.name}: no vehicle pose (LOCAL_POSITION_NED + ATTITUDE) for "
                              f"{POSE_TIMEOUT_S:.0f} s")
            time.sleep(0.02)

    def close(self) -> None:
        self.provider.close()
