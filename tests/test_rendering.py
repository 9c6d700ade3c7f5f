"""Bird's-eye rendering: views, map raster, agents/signals per frame, videos, real scenario."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from tbsim_env.core.constants import (
    NUM_TL_STATES,
    MapFeatureType,
    ObjectType,
    RoadEdgeType,
    RoadLineType,
    SignalState,
    TLState,
)
from tbsim_env.data.scenario import RoadMap, Scenario, Tracks, TrafficSignals
from tbsim_env.rendering import (
    GROUP_COLORS,
    TL_COLORS,
    AgentGroup,
    AgentLayer,
    MapLayer,
    SignalLayer,
    View,
    follow,
    log_groups,
    render_frame,
    render_log_frame,
    render_log_video,
    render_map,
    render_state,
    view_for,
    write_video,
)
from tbsim_env.rendering import palette as P
from tbsim_env.rendering.map_layer import dash_runs, offset_polyline
from tbsim_env.sim.state import AgentInfo, LogTrajectory, RoadEdges, SignalLog, SimState

ORIGIN = np.array([1000.0, -2000.0])
"""Scenario-frame offset of the synthetic road (real WOMD coordinates are far from 0)."""


def _road_map(features: list[tuple[MapFeatureType, int, np.ndarray]]) -> RoadMap:
    return RoadMap.from_polylines(
        np.arange(len(features)),
        [int(k) for k, _, _ in features],
        [s for _, s, _ in features],
        [np.concatenate([p + ORIGIN, np.zeros((len(p), 1))], axis=1) for _, _, p in features],
    )


def synthetic_scenario(num_steps: int = 12) -> Scenario:
    """A straight 200 m east-west road (edges at y = +-8 m) with 3 tracks and 2 signals."""
    xs = np.linspace(-100.0, 100.0, 81)
    line = lambda y: np.stack([xs, np.full_like(xs, y)], axis=1)  # noqa: E731
    crosswalk = np.array([[30.0, -8.0], [34.0, -8.0], [34.0, 8.0], [30.0, 8.0]])
    features = [
        (MapFeatureType.LANE, 2, line(-4.0)),
        (MapFeatureType.LANE, 2, line(4.0)),
        (MapFeatureType.ROAD_LINE, int(RoadLineType.SOLID_DOUBLE_YELLOW), line(0.0)),
        (MapFeatureType.ROAD_EDGE, int(RoadEdgeType.BOUNDARY), line(-8.0)),
        (MapFeatureType.ROAD_EDGE, int(RoadEdgeType.BOUNDARY), line(8.0)),
        (MapFeatureType.CROSSWALK, 0, crosswalk),
        (MapFeatureType.STOP_SIGN, 0, np.array([[-20.0, 10.0]])),
    ]
    a, t = 3, num_steps
    xyz = np.zeros((a, t, 3))
    xyz[0, :, 0] = np.linspace(-30.0, -20.0, t)  # SDC driving east in the lower lane
    xyz[0, :, 1] = -4.0
    xyz[1, :, 0] = np.linspace(20.0, 10.0, t)  # driving west in the upper lane
    xyz[1, :, 1] = 4.0
    xyz[2, :, 0] = 32.0  # pedestrian crossing northwards
    xyz[2, :, 1] = np.linspace(-6.0, 6.0, t)
    xyz[..., :2] += ORIGIN
    heading = np.zeros((a, t), np.float32)
    heading[1] = -np.pi
    heading[2] = np.pi / 2
    size = np.zeros((a, t, 3), np.float32)
    size[:2] = (4.5, 2.0, 1.6)
    size[2] = (0.6, 0.6, 1.8)
    valid = np.ones((a, t), bool)
    valid[1, t - 2 :] = False
    tracks = Tracks(
        id=np.array([7, 8, 9], np.int64),
        object_type=np.array([1, 1, 2], np.int8),
        xyz=xyz,
        heading=heading,
        velocity=np.zeros((a, t, 2), np.float32),
        size=size,
        valid=valid,
    )
    signals = TrafficSignals(
        lane_id=np.array([0, 1], np.int64),
        state=np.stack(
            [
                np.full(t, int(SignalState.STOP), np.int8),
                np.full(t, int(SignalState.GO), np.int8),
            ]
        ),
        valid=np.ones((2, t), bool),
        stop_point=np.array([[25.0, -4.0, 0.0], [40.0, 4.0, 0.0]]) + [*ORIGIN, 0.0],
    )
    return Scenario(
        scenario_id="synthetic",
        timestamps=np.arange(t) * 0.1,
        current_index=min(10, t - 1),
        tracks=tracks,
        road_map=_road_map(features),
        signals=signals,
        sdc_index=0,
        tracks_to_predict=np.array([1], np.int64),
        predict_difficulty=np.array([1], np.int8),
        objects_of_interest=np.zeros(0, np.int64),
    ).validate()


@pytest.fixture(scope="module")
def scenario() -> Scenario:
    return synthetic_scenario()


@pytest.fixture(scope="module")
def view() -> View:
    return View((float(ORIGIN[0]), float(ORIGIN[1])), 0.25, 160, 240)  # 60 m x 40 m


@pytest.fixture(scope="module")
def layer(scenario: Scenario, view: View) -> MapLayer:
    return MapLayer.build(scenario, view, pad_m=20.0)


def pix(view: View, xy_local: tuple[float, float]) -> tuple[int, int]:
    """(row, col) of the pixel holding a point given relative to ORIGIN."""
    u, v = view.to_pixels(np.asarray(xy_local) + ORIGIN)
    return int(np.floor(v)), int(np.floor(u))


def colour_close(px: np.ndarray, rgb: tuple[int, ...], tol: int = 6) -> bool:
    return bool(np.abs(px.astype(int) - np.asarray(rgb[:3])).max() <= tol)


def near(img: np.ndarray, rc: tuple[int, int], rgb: tuple[int, ...]) -> bool:
    """Whether a pixel within one row/column of ``rc`` has colour ``rgb``."""
    r, c = rc
    patch = img[r - 1 : r + 2, c - 1 : c + 2].reshape(-1, 3).astype(int)
    return bool((np.abs(patch - np.asarray(rgb[:3])).max(axis=1) == 0).any())


def one_agent(layer: MapLayer, xy, yaw=0.0, size=(4.5, 2.0), group=AgentGroup.POLICY, **kw):
    agents = AgentLayer(
        xy=np.asarray([xy], float) + ORIGIN,
        yaw=np.array([yaw]),
        size=np.array([size]),
        valid=np.array([kw.pop("valid", True)]),
        group=np.array([int(group)]),
        type=kw.pop("agent_type", None),
        trails=kw.pop("trails", None),
        trail_valid=kw.pop("trail_valid", None),
    )
    signals = None
    if "signal_xy" in kw:
        state, valid = kw.pop("signal_state"), kw.pop("signal_valid", None)
        signals = SignalLayer(kw.pop("signal_xy"), state, valid)
    return render_frame(
        layer,
        agents,
        signals,
        legend=False,
        **kw,
    )


# --------------------------------------------------------------------------- view
def test_view_pixels_north_up_and_inverse(view: View) -> None:
    c = np.array(view.center)
    np.testing.assert_allclose(view.to_pixels(c), [view.width / 2, view.height / 2])
    east, north = view.to_pixels(c + [10.0, 0.0]), view.to_pixels(c + [0.0, 10.0])
    assert east[0] == pytest.approx(view.width / 2 + 40) and east[1] == view.height / 2
    assert north[1] == pytest.approx(view.height / 2 - 40)  # +y is up in the image
    pts = np.random.default_rng(0).normal(size=(5, 2)) * 30 + c
    np.testing.assert_allclose(view.to_world(view.to_pixels(pts)), pts)
    assert view.extent == pytest.approx((c[0] - 30, c[0] + 30, c[1] - 20, c[1] + 20))
    with pytest.raises(ValueError, match="meters_per_pixel"):
        View((0.0, 0.0), 0.0, 10, 10)


def test_follow_keeps_zoom_and_size(view: View) -> None:
    moved = follow(view, np.array([5.0, 6.0]))
    assert moved.center == (5.0, 6.0)
    assert (moved.meters_per_pixel, moved.size) == (view.meters_per_pixel, view.size)


def test_view_for_small_map_is_whole_map(scenario: Scenario) -> None:
    # The synthetic map is 200 m wide: too big for "small", so it is SDC centred.
    v = view_for(scenario, (300, 400), margin=5.0)
    sdc_now = scenario.tracks.xyz[0, scenario.current_index, :2]
    assert v.center == pytest.approx(tuple(sdc_now))
    x0, x1, y0, y1 = v.extent
    pts = scenario.tracks.xyz[:2, :, :2].reshape(-1, 2)  # SDC and the track to predict
    assert (pts[:, 0] > x0).all() and (pts[:, 0] < x1).all()
    assert (pts[:, 1] > y0).all() and (pts[:, 1] < y1).all()
    whole = view_for(scenario, (300, 400), small_map_m=500.0)
    assert whole.center == pytest.approx(tuple(ORIGIN + [0.0, 1.0]))  # map y in [-8, 10]
    assert whole.width_m >= 200.0


# --------------------------------------------------------------------------- map layer
def test_dash_runs_and_offsets() -> None:
    runs = dash_runs(np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]]), dash=3.0, gap=6.0)
    spans = [(r[0, 0], r[-1, 0]) for r in runs]
    assert spans == [(0.0, 3.0), (9.0, 12.0), (18.0, 20.0)]
    left = offset_polyline(np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]), 0.5)
    np.testing.assert_allclose(left[:, 1], 0.5)


def test_map_layer_draws_features(scenario: Scenario, view: View, layer: MapLayer) -> None:
    img = layer.image
    assert img.shape == (160, 240, 3) and img.dtype == np.uint8
    assert len(np.unique(img.reshape(-1, 3), axis=0)) >= 6
    # Road edges (y = +-8 m) are dark where they project, empty ground is background.
    for x in (-25.0, 0.0, 17.0):
        for y in (-8.0, 8.0):
            assert colour_close(img[pix(view, (x, y))], P.ROAD_EDGE_BOUNDARY, tol=20)
    assert colour_close(img[pix(view, (0.0, 15.0))], P.BACKGROUND, tol=0)
    assert colour_close(img[pix(view, (0.0, -2.0))], P.BACKGROUND, tol=0)
    # Solid double yellow: two yellow strokes beside y = 0 (0.2 m each side = 0.8 px).
    col = pix(view, (5.0, 0.0))[1]
    strip = img[pix(view, (5.0, 0.6))[0] : pix(view, (5.0, -0.6))[0] + 1, col].astype(int)
    yellowish = (strip[:, 0] > 150) & (strip[:, 1] > 120) & (strip[:, 2] < 110)
    assert yellowish.any()
    # Lane centre line (y = -4) is lighter than the ground.
    assert img[pix(view, (0.0, -4.0))].astype(int).sum() > sum(P.BACKGROUND) + 30
    # Translucent crosswalk at x in [30, 34] lies outside this view; the stop sign is inside.
    assert colour_close(img[pix(view, (-20.0, 10.0))], P.STOP_SIGN, tol=30)
    # render_map for the same view is the same raster.
    np.testing.assert_array_equal(render_map(scenario, view), img)


def test_map_layer_crosswalk_is_translucent(scenario: Scenario, view: View) -> None:
    img = render_map(scenario, follow(view, ORIGIN + [32.0, 0.0]))
    v = follow(view, ORIGIN + [32.0, 0.0])
    px = img[pix(v, (32.0, -6.0))].astype(int)
    bg = np.array(P.BACKGROUND)
    assert (px > bg + 20).all() and (px < np.array(P.CROSSWALK[:3])).all()


def test_map_layer_follow_crops_canvas(scenario: Scenario, view: View, layer: MapLayer) -> None:
    moved = follow(view, np.array(view.center) + [5.0, -2.5])  # a whole number of pixels
    crop = layer.background(moved)
    direct = render_map(scenario, moved)
    assert crop.shape == direct.shape
    assert np.abs(crop.astype(int) - direct).mean() < 0.5
    # Outside the padded canvas the background colour fills in.
    far = layer.background(follow(view, np.array(view.center) + [500.0, 0.0]))
    assert (far == np.array(P.BACKGROUND, np.uint8)).all()
    with pytest.raises(ValueError, match="resolution"):
        layer.background(View(view.center, 0.5, 10, 10))


# --------------------------------------------------------------------------- agents
def test_agent_drawn_in_group_colour_and_moves(view: View, layer: MapLayer) -> None:
    bg = layer.image
    for group in AgentGroup:
        img = one_agent(layer, (-10.0, -4.0), group=group)
        assert img.shape == (160, 240, 3) and img.dtype == np.uint8
        # Rear half, off the heading tick.
        assert colour_close(img[pix(view, (-11.5, -4.5))], GROUP_COLORS[group], tol=0)
    moved = one_agent(layer, (10.0, 4.0))
    assert colour_close(moved[pix(view, (8.5, 3.5))], GROUP_COLORS[AgentGroup.POLICY], tol=0)
    np.testing.assert_array_equal(moved[pix(view, (-11.5, -4.5))], bg[pix(view, (-11.5, -4.5))])


def test_agent_orientation_and_heading_tick(view: View, layer: MapLayer) -> None:
    fill = GROUP_COLORS[AgentGroup.POLICY]
    east = one_agent(layer, (0.0, -4.0), yaw=0.0, size=(8.0, 2.0))
    assert colour_close(east[pix(view, (3.0, -4.6))], fill, tol=0)  # long along x
    assert not colour_close(east[pix(view, (0.3, -7.0))], fill)  # narrow along y
    assert near(east, pix(view, (2.5, -4.0)), P.HEADING_TICK)  # tick in front
    assert not near(east, pix(view, (-2.5, -4.0)), P.HEADING_TICK)  # no tick behind
    north = one_agent(layer, (0.0, -4.0), yaw=np.pi / 2, size=(8.0, 2.0))
    assert colour_close(north[pix(view, (0.6, -1.0))], fill, tol=0)  # long along y
    assert near(north, pix(view, (0.0, -1.5)), P.HEADING_TICK)  # tick is up
    assert not near(north, pix(view, (0.0, -6.5)), P.HEADING_TICK)
    r_tip, _ = pix(view, (0.0, -0.5))
    r_tail, _ = pix(view, (0.0, -7.5))
    assert r_tip < r_tail  # north is up in the image


def test_invalid_agents_not_drawn(layer: MapLayer) -> None:
    img = one_agent(layer, (-10.0, -4.0), valid=False)
    np.testing.assert_array_equal(img, layer.image)
    nan = one_agent(layer, (np.nan, -4.0))
    np.testing.assert_array_equal(nan, layer.image)


def test_pedestrian_disc(view: View, layer: MapLayer) -> None:
    img = one_agent(
        layer, (5.0, 5.0), size=(0.6, 0.6), agent_type=np.array([int(ObjectType.PEDESTRIAN)])
    )
    fill = GROUP_COLORS[AgentGroup.POLICY]
    assert colour_close(img[pix(view, (4.8, 4.8))], fill, tol=0)
    assert not colour_close(img[pix(view, (5.0, 6.0))], fill)


def test_trails_drawn_under_agent(view: View, layer: MapLayer) -> None:
    trail = np.stack([np.linspace(-20.0, -12.0, 9), np.full(9, -6.0)], axis=1) + ORIGIN
    trail_valid = np.ones(9, bool)
    trail_valid[:4] = False  # x in [-20, -17] is hidden
    img = one_agent(
        layer, (-10.0, -4.0), trails=trail[None], trail_valid=trail_valid[None], title=None
    )
    bg = layer.image
    shown, hidden = pix(view, (-14.0, -6.0)), pix(view, (-19.0, -6.0))
    assert np.abs(img[shown].astype(int) - bg[shown]).sum() > 30
    np.testing.assert_array_equal(img[hidden], bg[hidden])


def test_input_checks(layer: MapLayer) -> None:
    with pytest.raises(ValueError, match="agent_group"):
        one_agent(layer, (0.0, 0.0), group=7)
    with pytest.raises(ValueError, match="agent_yaw"):
        render_frame(
            layer,
            AgentLayer(
                xy=np.zeros((2, 2)),
                yaw=np.zeros(3),
                size=np.ones((2, 2)),
                valid=np.ones(2, bool),
                group=np.zeros(2, int),
            ),
        )
    with pytest.raises(ValueError, match="signal_state"):
        one_agent(layer, (0.0, 0.0), signal_xy=np.zeros((1, 2)), signal_state=np.array([9]))


# --------------------------------------------------------------------------- signals, text
def test_signal_colours_per_state(view: View, layer: MapLayer) -> None:
    xs = np.array([-20.0, -10.0, 0.0, 10.0, 20.0])
    sxy = np.stack([xs, np.full(5, 4.0)], axis=1) + ORIGIN
    state = np.arange(NUM_TL_STATES)
    valid = np.ones(5, bool)
    valid[4] = False
    img = one_agent(layer, (0.0, -100.0), signal_xy=sxy, signal_state=state, signal_valid=valid)
    for x, s in zip(xs[:4], state[:4]):
        assert colour_close(img[pix(view, (x, 4.0))], TL_COLORS[TLState(s)], tol=0)
    np.testing.assert_array_equal(img[pix(view, (20.0, 4.0))], layer.image[pix(view, (20.0, 4.0))])


def test_title_and_legend_change_corners(layer: MapLayer) -> None:
    plain = one_agent(layer, (0.0, 0.0))
    titled = one_agent(layer, (0.0, 0.0), title="t = 3.4 s")
    assert (titled[:20, :60] != plain[:20, :60]).any()
    np.testing.assert_array_equal(titled[60:, :], plain[60:, :])
    agents = AgentLayer(
        xy=np.array([ORIGIN]),
        yaw=np.zeros(1),
        size=np.ones((1, 2)),
        valid=np.ones(1, bool),
        group=np.array([int(AgentGroup.SDC)]),
    )
    legend = render_frame(layer, agents, legend=True)
    assert (legend[-30:, :60] != render_frame(layer, agents, legend=False)[-30:, :60]).any()


# --------------------------------------------------------------------------- SimState
def _make(cls, n: int, **known):
    """Build a state dataclass; fields this test does not know get [1, N] int64 zeros."""
    names = [f.name for f in dataclasses.fields(cls)]
    return cls(**{k: known.get(k, torch.zeros(1, n, dtype=torch.long)) for k in names})


def _sim_state(scenario: Scenario, step: int) -> SimState:
    """A B=1 SimState of the synthetic log, shifted by an origin."""
    t = scenario.tracks
    origin = torch.from_numpy(ORIGIN)[None]
    xy = torch.from_numpy(t.xyz[:, :, :2] - ORIGIN).float()
    pose = torch.cat([xy, torch.from_numpy(t.heading)[..., None]], dim=-1)[None]
    valid = torch.from_numpy(t.valid)[None]
    n, steps = t.num_tracks, t.num_steps
    sig = scenario.signals
    return _make(
        SimState,
        n,
        step=torch.tensor([step]),
        pose=pose[:, :, step],
        speed=torch.zeros(1, n),
        valid=valid[:, :, step],
        controlled=torch.tensor([[False, True, False]]),
        agents=_make(
            AgentInfo,
            n,
            track_id=torch.from_numpy(t.id)[None],
            track_index=torch.arange(n)[None],
            object_type=torch.from_numpy(t.object_type.astype(np.int64))[None],
            size=torch.from_numpy(t.size[:, step])[None],
            role=torch.from_numpy(scenario.role_mask())[None],
            mask=torch.ones(1, n, dtype=torch.bool),
        ),
        log=_make(
            LogTrajectory,
            n,
            pose=pose,
            speed=torch.zeros(1, n, steps),
            velocity=torch.zeros(1, n, steps, 2),
            z=torch.zeros(1, n, steps),
            valid=valid,
        ),
        signals=_make(
            SignalLog,
            n,
            lane_id=torch.from_numpy(sig.lane_id)[None],
            state=torch.tensor([[1, 3]]).repeat_interleave(steps, dim=1).view(1, 2, steps),
            valid=torch.from_numpy(sig.valid)[None],
            stop_point=torch.from_numpy(sig.stop_point[:, :2] - ORIGIN).float()[None],
        ),
        road_edges=_make(
            RoadEdges,
            n,
            start=torch.zeros(1, 0, 2),
            end=torch.zeros(1, 0, 2),
            valid=torch.zeros(1, 0, dtype=torch.bool),
        ),
        origin=origin,
    )


def test_render_state_adds_origin(scenario: Scenario, view: View) -> None:
    layer = MapLayer.build(scenario, follow(view, ORIGIN + [0.0, 0.0]), pad_m=0.0)
    state = _sim_state(scenario, 5)
    img = render_state(layer, state, 0, legend=False)
    assert img.shape == (160, 240, 3) and img.dtype == np.uint8
    t = scenario.tracks
    sdc_xy = t.xyz[0, 5, :2] - ORIGIN - [1.5, 0.5]  # rear part of the SDC box
    assert colour_close(img[pix(view, tuple(sdc_xy))], GROUP_COLORS[AgentGroup.SDC], tol=0)
    npc_xy = t.xyz[1, 5, :2] - ORIGIN + [1.5, 0.5]  # heading west: rear is east
    assert colour_close(img[pix(view, tuple(npc_xy))], GROUP_COLORS[AgentGroup.POLICY], tol=0)
    # Signals: lane 0 STOP at (25, -4), lane 1 GO at (40, 4) is outside the 60 m view.
    assert colour_close(img[pix(view, (25.0, -4.0))], TL_COLORS[TLState.STOP], tol=0)
    groups = np.full(3, int(AgentGroup.EXTERNAL))
    ext = render_state(layer, state, 0, groups, title="", legend=False)
    assert colour_close(ext[pix(view, tuple(sdc_xy))], GROUP_COLORS[AgentGroup.EXTERNAL], tol=0)
    # Trails (positions, valid): drawn where valid only.
    trail = np.repeat(t.xyz[:, None, 5, :2], 4, axis=1) + [[-8.0, 0.0]]  # scenario frame
    trail = trail + np.linspace(0.0, 6.0, 4)[None, :, None] * [1.0, 0.0]
    trail_valid = np.ones((3, 4), bool)
    with_trails = render_state(layer, state, 0, legend=False, trails=(trail, trail_valid))
    hidden = render_state(layer, state, 0, legend=False, trails=(trail, ~trail_valid))
    assert not np.array_equal(with_trails, img) and np.array_equal(hidden, img)
    with pytest.raises(IndexError):
        render_state(layer, state, 1)


def test_render_log_frame_groups(scenario: Scenario) -> None:
    v = view_for(scenario, (120, 160))
    layer = MapLayer.build(scenario, v)
    np.testing.assert_array_equal(log_groups(scenario), [3, 0, 0])
    last = render_log_frame(layer, scenario, scenario.num_steps - 1, trail_steps=5)
    assert last.shape == (120, 160, 3)
    with pytest.raises(IndexError):
        render_log_frame(layer, scenario, scenario.num_steps)


# --------------------------------------------------------------------------- video
def _frames(n: int, h: int = 31, w: int = 45) -> list[np.ndarray]:
    frames = []
    for i in range(n):
        f = np.zeros((h, w, 3), np.uint8)
        f[:, : (i + 1) * 5] = (200, 40, 40)
        frames.append(f)
    return frames


def test_write_video_mp4_and_gif(tmp_path) -> None:
    import imageio.v2 as iio2
    import imageio.v3 as iio

    frames = _frames(6)
    assert write_video(iter(frames), tmp_path / "a.mp4", fps=10) == 6
    reader = iio2.get_reader(str(tmp_path / "a.mp4"), format="FFMPEG")
    back = np.stack([f for f in reader])  # list(reader) asks len() = inf
    reader.close()
    assert back.shape == (6, 32, 46, 3)  # padded to even sizes for yuv420p
    assert abs(int(back[5, 10, 20, 0]) - 200) < 30 and int(back[0, 10, 40, 0]) < 30

    assert write_video(frames, tmp_path / "sub" / "a.GIF", fps=5) == 6
    gif = iio.imread(tmp_path / "sub" / "a.GIF", index=None)
    assert gif.shape[:3] == (6, 31, 45)
    np.testing.assert_array_equal(gif[3][..., :3], frames[3])


def test_write_video_errors(tmp_path) -> None:
    with pytest.raises(ValueError, match="unknown extension '.avi'"):
        write_video(_frames(2), tmp_path / "a.avi")
    with pytest.raises(ValueError, match="no frames"):
        write_video([], tmp_path / "a.gif")
    with pytest.raises(ValueError, match="frame 1 has shape"):
        write_video([_frames(1)[0], _frames(1, 30, 44)[0]], tmp_path / "b.mp4")
    with pytest.raises(ValueError, match="uint8"):
        write_video([np.zeros((4, 4, 3))], tmp_path / "c.gif")


# --------------------------------------------------------------------------- real data
def _load_real(path):
    try:
        from tbsim_env.data import load_scenarios
    except ImportError:
        pytest.skip("tbsim_env.data.load_scenarios is not available yet")
    return next(iter(load_scenarios(path)))


def test_real_scenario_frame_and_video(one_scenario_path, tmp_path) -> None:
    import imageio.v2 as iio2

    scn = _load_real(one_scenario_path)
    view = view_for(scn, (600, 600))
    layer = MapLayer.build(scn, view)
    assert len(np.unique(layer.image.reshape(-1, 3), axis=0)) > 20
    frame = render_log_frame(layer, scn, scn.current_index)
    assert frame.shape == (600, 600, 3) and frame.dtype == np.uint8
    # The SDC sits at the view centre at the current step, in the SDC colour.
    sdc = scn.tracks
    assert view.center == pytest.approx(tuple(sdc.xyz[scn.sdc_index, scn.current_index, :2]))
    yaw = float(sdc.heading[scn.sdc_index, scn.current_index])
    rear = np.array(view.center) - 1.0 * np.array([np.cos(yaw), np.sin(yaw)])
    u, v = view.to_pixels(rear)
    assert colour_close(frame[int(v), int(u)], GROUP_COLORS[AgentGroup.SDC], tol=0)

    out = render_log_video(scn, tmp_path / "log.mp4", size=(200, 300), progress=False)
    reader = iio2.get_reader(str(out), format="FFMPEG")
    n = sum(1 for _ in reader)
    meta_size = reader.get_meta_data()["size"]
    reader.close()
    assert n == scn.num_steps and tuple(meta_size) == (300, 200)


def test_real_scenario_render_state_matches_log(one_scenario_path) -> None:
    build = pytest.importorskip("tbsim_env.sim.build")
    scn = _load_real(one_scenario_path)
    state = build.build_sim_state([scn])
    assert np.abs(state.origin.numpy()).max() > 100.0  # the shift really is exercised
    layer = MapLayer.build(scn, view_for(scn, (300, 300)))
    step = int(state.step[0])
    from_state = render_state(layer, state, 0, title="x")
    from_log = render_log_frame(layer, scn, step, trail_steps=0, title="x")
    assert from_state.shape == (300, 300, 3)
    # Same poses, sizes, groups and signals: the images agree up to a few edge pixels
    # (float32 state positions, sizes averaged over the log vs per step).
    differ = np.abs(from_state.astype(int) - from_log).max(axis=-1) > 0
    assert differ.mean() < 0.01
    assert (from_state != layer.image).any(axis=-1).mean() > 0.01


def test_render_command_shows_the_whole_scenario_with_trafficbots(
    one_scenario_path, tmp_path, capsys
) -> None:
    """On this scene a TrafficBots NPC runs into the log-following SDC within 3 s; the video
    still covers all 8 s after the current step (81 frames), the collision drawn, not an end."""
    from tbsim_env.cli import main

    out = tmp_path / "r.gif"
    rc = main(["render", str(one_scenario_path), "--npc-policy", "trafficbots", "--out", str(out)])
    assert rc == 0 and out.exists()
    assert "(81 frames)" in capsys.readouterr().out


def test_demo_command_writes_one_video_per_embedded_scene(tmp_path, capsys) -> None:
    """The README's first command (``tbsim demo``), short: each video starts on its own scene."""
    import imageio.v2 as iio2

    from tbsim_env.cli import main

    out = tmp_path / "demo.gif"
    assert main(["demo", "--out", str(out), "--scenarios", "2", "--steps", "4"]) == 0
    printed = capsys.readouterr().out
    videos = [tmp_path / "demo_0.gif", tmp_path / "demo_1.gif"]
    assert all(v.exists() for v in videos) and printed.count("(5 frames)") == 2
    first = [iio2.mimread(str(v))[0] for v in videos]
    assert not np.array_equal(first[0], first[1])  # two different scenes
