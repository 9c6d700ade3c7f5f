"""The rollout viewer in a real headless browser: Debian's Chromium driven by Selenium.

Needs ``chromium`` and ``chromium-driver`` (``apt-get install chromium chromium-driver``) and
``selenium`` (the test extra). Without them the tests skip with the reason; under ``CI=true``
(where ``.ci/run`` installs them) a missing browser is a failure.
"""

from __future__ import annotations

import io
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from tbsim_env.data import load_scenarios
from tbsim_env.evaluation import make_rollout_fn
from tbsim_env.rendering import GROUP_COLORS, AgentGroup
from tbsim_env.rendering.viewer import log_rollout, simulated_rollouts, write_viewer

CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--force-device-scale-factor=1",
    "--window-size=1400,1000",
)
"""No network here: without these Chromium waits on connections it cannot make."""


def _browser_paths() -> tuple[str, str]:
    """(chromium, chromedriver), or skip (fail under CI) naming what is missing."""
    missing = []
    try:
        import selenium  # noqa: F401
    except ImportError:
        missing.append("the selenium package (pip install -e '.[test]')")
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if chromium is None:
        missing.append("chromium (apt-get install chromium)")
    if driver is None:
        missing.append("chromedriver (apt-get install chromium-driver)")
    if missing:
        msg = "headless browser test needs " + ", ".join(missing)
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg + "; .ci/run installs them under CI")
        pytest.skip(msg)
    return chromium, driver


@pytest.fixture(scope="module")
def driver(tmp_path_factory):
    chromium, chromedriver = _browser_paths()
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for flag in CHROMIUM_FLAGS:
        options.add_argument(flag)
    options.add_argument(f"--user-data-dir={tmp_path_factory.mktemp('chromium-profile')}")
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    drv = webdriver.Chrome(service=Service(chromedriver), options=options)
    drv.set_page_load_timeout(60)
    yield drv
    drv.quit()


@pytest.fixture(scope="module")
def scene(one_scenario_path: Path, tmp_path_factory, torch_one_thread):
    """(scenario, rollouts, html path): 2 constant-velocity rollouts and the log."""
    sc = load_scenarios(one_scenario_path)[0]
    rollouts = make_rollout_fn("constant_velocity")(sc, 2, 0)
    path = tmp_path_factory.mktemp("viewer") / "view.html"
    write_viewer(path, sc, [*simulated_rollouts(sc, rollouts), log_rollout(sc)], "browser test")
    return sc, rollouts, path


@pytest.fixture
def page(driver, scene):
    driver.get(scene[2].as_uri())
    assert driver.execute_script("return window.TBSIM && window.TBSIM.ready") is True
    return driver


def _pixel(data: dict, x: float, y: float) -> tuple[float, float]:
    """Scenario-frame metres to canvas pixels, by the camera the page embeds (computed here)."""
    v = data["view"]
    return ((x - v["cx"]) / v["mpp"] + v["width"] / 2, v["height"] / 2 - (y - v["cy"]) / v["mpp"])


def _screenshot(driver) -> np.ndarray:
    from PIL import Image

    canvas = driver.find_element("id", "scene")
    img = np.asarray(Image.open(io.BytesIO(canvas.screenshot_as_png)).convert("RGB")).astype(int)
    top, left = driver.execute_script(
        "const c = arguments[0]; return [c.clientTop, c.clientLeft];", canvas
    )  # the element's screenshot includes its border
    return img[top : img.shape[0] - top, left : img.shape[1] - left]


def _colour_share(img: np.ndarray, uv: tuple[float, float], rgb, half: int = 2) -> float:
    """Share of the pixels in a (2 half + 1)^2 square around ``uv`` within 12 of ``rgb``."""
    u, v = int(round(uv[0])), int(round(uv[1]))
    patch = img[v - half : v + half + 1, u - half : u + half + 1]
    return float((np.abs(patch - np.array(rgb)).max(-1) <= 12).mean())


def _rear_point(sc, a: int, x: float, y: float, yaw: float) -> tuple[float, float]:
    """A point between the box centre and its rear (clear of the heading tick), metres."""
    back = 0.25 * float(sc.tracks.size[a, sc.current_index, 0])
    return x - back * np.cos(yaw), y - back * np.sin(yaw)


def test_page_loads_without_console_errors(page) -> None:
    logs = page.get_log("browser")
    assert not [e for e in logs if e["level"] in ("SEVERE", "ERROR")], logs
    assert page.find_element("id", "heading").text.startswith("scenario 637f20cafde22ff8")
    options = page.find_elements("css selector", "#rollout option")
    assert [o.text for o in options] == ["rollout 0", "rollout 1", "log"]
    assert page.execute_script("return TBSIM.drawn.length") > 10


def _mover(sc, rollouts, data: dict) -> tuple[int, int]:
    """(track, rollout row) of the sim agent that moves farthest on the canvas in rollout 0."""
    w, h = data["view"]["width"], data["view"]["height"]
    best, best_d = None, 0.0
    for k, oid in enumerate(rollouts.object_id.tolist()):
        a = int(np.flatnonzero(sc.tracks.id == oid)[0])
        uv0 = _pixel(data, *sc.tracks.xyz[a, sc.current_index, :2])
        uv1 = _pixel(data, float(rollouts.x[0, k, -1]), float(rollouts.y[0, k, -1]))
        inside = all(20 < p[0] < w - 20 and 20 < p[1] < h - 20 for p in (uv0, uv1))
        d = float(np.hypot(uv1[0] - uv0[0], uv1[1] - uv0[1]))
        if inside and d > best_d:
            best, best_d = (a, k), d
    assert best is not None and best_d > 50
    return best


def test_slider_moves_agents(page, scene) -> None:
    from selenium.webdriver.common.keys import Keys

    sc, rollouts, _ = scene
    data = page.execute_script("return TBSIM.data")
    a, k = _mover(sc, rollouts, data)
    oid = int(sc.tracks.id[a])

    def drawn_at():
        drawn = page.execute_script("return TBSIM.drawn")
        return next((d["u"], d["v"]) for d in drawn if d["id"] == oid)

    assert page.execute_script("return TBSIM.state.step") == sc.current_index
    before = drawn_at()
    np.testing.assert_allclose(
        before, _pixel(data, *sc.tracks.xyz[a, sc.current_index, :2]), atol=0.5
    )
    page.find_element("id", "time").send_keys(Keys.END)  # a user's key press on the slider
    last = data["num_steps"] - 1
    assert page.execute_script("return TBSIM.state.step") == last
    after = drawn_at()
    expected = _pixel(data, float(rollouts.x[0, k, -1]), float(rollouts.y[0, k, -1]))
    np.testing.assert_allclose(after, expected, atol=0.5)
    assert np.hypot(after[0] - before[0], after[1] - before[1]) > 50
    assert f"step {last}" in page.find_element("id", "clock").text
    page.find_element("id", "time").send_keys(Keys.ARROW_LEFT)
    assert page.execute_script("return TBSIM.state.step") == last - 1


def test_click_agent_shows_info(page, scene) -> None:
    from selenium.webdriver.common.action_chains import ActionChains

    sc, _, _ = scene
    data = page.execute_script("return TBSIM.data")
    a, cur = sc.sdc_index, sc.current_index
    x, y, yaw = *sc.tracks.xyz[a, cur, :2], sc.tracks.heading[a, cur]
    u, v = _pixel(data, *_rear_point(sc, a, x, y, yaw))
    canvas = page.find_element("id", "scene")
    w, h = data["view"]["width"], data["view"]["height"]
    ActionChains(page).move_to_element_with_offset(canvas, u - w / 2, v - h / 2).click().perform()
    assert page.execute_script("return TBSIM.state.selected") == a
    text = page.find_element("id", "info-body").text
    speed = data["rollouts"][0]["speed"][a][cur]
    assert f"id {int(sc.tracks.id[a])}" in text and "type vehicle" in text
    assert "controller SDC" in text and f"speed {speed:.2f} m/s" in text
    collided = "yes" if data["rollouts"][0]["collision"][a] else "no"
    off = "yes" if data["rollouts"][0]["offroad"][a] else "no"
    assert f"collision {collided}" in text and f"off-road {off}" in text
    ActionChains(page).move_to_element_with_offset(canvas, -w / 2 + 3, -h / 2 + 3).click().perform()
    assert page.execute_script("return TBSIM.state.selected") == -1


def test_screenshot_matches_scene(page, scene) -> None:
    """Agents' colours lie where their logged / simulated positions project, and move."""
    from selenium.webdriver.support.ui import Select

    sc, rollouts, _ = scene
    data = page.execute_script("return TBSIM.data")
    t, cur = sc.tracks, sc.current_index
    sdc = sc.sdc_index
    img = _screenshot(page)
    assert img.shape[:2] == (data["view"]["height"], data["view"]["width"])
    sdc_rgb = GROUP_COLORS[AgentGroup.SDC]
    start = _pixel(data, *_rear_point(sc, sdc, *t.xyz[sdc, cur, :2], t.heading[sdc, cur]))
    assert _colour_share(img, start, sdc_rgb) > 0.8
    # The other vehicles on the canvas: policy colour in rollout 0, log colour in "log".
    w, h = data["view"]["width"], data["view"]["height"]
    on_canvas = [
        (a, _pixel(data, *_rear_point(sc, a, *t.xyz[a, cur, :2], t.heading[a, cur])))
        for a in np.flatnonzero(t.valid[:, cur] & (t.object_type == 1))
        if a != sdc
    ]
    on_canvas = [(a, uv) for a, uv in on_canvas if 10 < uv[0] < w - 10 and 10 < uv[1] < h - 10]
    assert len(on_canvas) > 10

    def found(image: np.ndarray, group: AgentGroup) -> int:
        return sum(_colour_share(image, uv, GROUP_COLORS[group], 1) > 0.5 for _, uv in on_canvas)

    # Overlapping boxes may hide a few; most must show their colour where they are.
    assert found(img, AgentGroup.POLICY) >= 0.8 * len(on_canvas)
    assert found(img, AgentGroup.LOG_REPLAY) == 0
    Select(page.find_element("id", "rollout")).select_by_visible_text("log")
    img = _screenshot(page)
    assert found(img, AgentGroup.LOG_REPLAY) >= 0.8 * len(on_canvas)
    assert found(img, AgentGroup.POLICY) == 0
    # Rollout 0 at its last step: the mover's colour is at its simulated end position.
    Select(page.find_element("id", "rollout")).select_by_visible_text("rollout 0")
    page.execute_script("TBSIM.setStep(TBSIM.data.num_steps - 1)")
    img = _screenshot(page)
    a, k = _mover(sc, rollouts, data)
    x, y, yaw = (float(v[0, k, -1]) for v in (rollouts.x, rollouts.y, rollouts.heading))
    rgb = GROUP_COLORS[AgentGroup.SDC if a == sdc else AgentGroup.POLICY]
    assert _colour_share(img, _pixel(data, *_rear_point(sc, a, x, y, yaw)), rgb) > 0.8
    old = _pixel(data, *_rear_point(sc, a, *t.xyz[a, cur, :2], t.heading[a, cur]))
    assert _colour_share(img, old, rgb) < 0.5


def test_play_and_pause(page, scene) -> None:
    import time

    from selenium.webdriver.support.ui import WebDriverWait

    sc = scene[0]
    play = page.find_element("id", "play")
    play.click()
    assert play.text == "Pause"
    WebDriverWait(page, 10).until(
        lambda d: d.execute_script("return TBSIM.state.step") >= sc.current_index + 3
    )
    play.click()
    assert play.text == "Play"
    stopped = page.execute_script("return TBSIM.state.step")
    time.sleep(0.5)
    assert page.execute_script("return TBSIM.state.step") == stopped
    assert f"step {stopped}" in page.find_element("id", "clock").text
