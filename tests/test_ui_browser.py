"""The web page in a real browser (headless Debian Chromium + selenium) against a real service.

One simulated capture (the simulator's `temporal` suite: a ceiling panel switches off at
frame 8) is uploaded through the page; the tests then use the finished job as a person
would: follow the progress to 100 %, click a pixel, read the env map, scrub time across the
switch, download the EXR. Screenshots go to tests/artifacts/ (gitignored).
"""
from __future__ import annotations

import math
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import TENANTS, running_stack, wait_until

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
ARTIFACTS = Path(__file__).parent / "artifacts"
KEY = TENANTS["alice"]

pytestmark = [
    pytest.mark.browser,
    pytest.mark.slow,
    pytest.mark.skipif(
        not CHROMIUM.exists(), reason="/usr/bin/chromium is absent (apt-get install chromium chromium-driver)"
    ),
    # without a local driver selenium would try to download one
    pytest.mark.skipif(
        not (CHROMEDRIVER.exists() or shutil.which("chromedriver")),
        reason="no chromedriver (apt-get install chromium-driver)",
    ),
]

# Enough steps for the draft field to learn the switch (24, the shared stack's setting, is not).
UI_DISTILL = '{"iterations": 200, "checkpoint_every": 1000, "work_height": 24, "warmup_steps": 4}'
SWITCH_FRAME = 8  # core.sim.suites.PANEL_OFF_FRAME
BEFORE_FRAME, AFTER_FRAME = 4, 12
CAPTURE_SIZE = (48, 36)
CLICK_UV = (0.5, 0.3)  # back wall, above the table
JOB_TIMEOUT_S = 240


# ---------------------------------------------------------------------------------------
# Fixtures: capture, service, browser
# ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def switch_capture(tmp_path_factory) -> tuple[Path, dict]:
    """The temporal suite at a tiny size: video.mp4 (written by core.io) + depth.npz."""
    from core.sim.capture import write_capture
    from core.sim.suites import PANEL_OFF_FRAME, suite

    assert PANEL_OFF_FRAME == SWITCH_FRAME
    out = tmp_path_factory.mktemp("switch")
    scene = suite("temporal").model_copy(update={"resolution": CAPTURE_SIZE})
    doc = write_capture(scene, out, probes=[], envmap_height=8, video=True)
    return out, doc


@pytest.fixture(scope="module")
def ui_stack(tmp_path_factory):
    with running_stack(tmp_path_factory.mktemp("ui-stack"), {"LIGHTFIELD_DISTILL_OVERRIDES": UI_DISTILL}) as stack:
        yield stack


@pytest.fixture(scope="module")
def downloads(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("downloads")


@pytest.fixture(scope="module")
def browser(tmp_path_factory, downloads):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--disable-dev-shm-usage", "--window-size=1440,1000",
                 f"--user-data-dir={tmp_path_factory.mktemp('chromium-profile')}"):
        options.add_argument(flag)
    options.add_experimental_option("prefs", {"download.default_directory": str(downloads),
                                              "download.prompt_for_download": False})
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    service = Service(executable_path=str(CHROMEDRIVER if CHROMEDRIVER.exists() else shutil.which("chromedriver")))
    driver = webdriver.Chrome(options=options, service=service)
    driver.execute_cdp_cmd("Browser.setDownloadBehavior", {"behavior": "allow", "downloadPath": str(downloads)})
    driver.set_script_timeout(30)
    try:
        yield driver
    finally:
        driver.quit()


def screenshot(driver, name: str) -> Path:
    ARTIFACTS.mkdir(exist_ok=True)
    path = ARTIFACTS / f"ui_{name}.png"
    driver.save_screenshot(str(path))
    return path


def text(driver, element_id: str) -> str:
    return driver.find_element("id", element_id).text


def wait_for(driver, condition: str, timeout_s: float = 30, what: str = "", *args):
    """Wait until a JS expression (a function body returning a truthy value) holds."""
    return wait_until(lambda: driver.execute_script(condition, *args), timeout_s, interval_s=0.1,
                      what=what or condition)


def image_pixels(driver, element_id: str) -> np.ndarray:
    """RGB pixels [H, W, 3] of a loaded <img> (blob: URLs are same-origin, so readable)."""
    data = driver.execute_script("""
        const img = document.getElementById(arguments[0]);
        const c = document.createElement('canvas');
        c.width = img.naturalWidth; c.height = img.naturalHeight;
        const g = c.getContext('2d'); g.drawImage(img, 0, 0);
        return [c.width, c.height, Array.from(g.getImageData(0, 0, c.width, c.height).data)];
    """, element_id)
    w, h, flat = data
    return np.asarray(flat, dtype=np.float32).reshape(h, w, 4)[..., :3] / 255.0


def hfov_deg(doc: dict) -> float:
    k = doc["intrinsics"]
    return math.degrees(2.0 * math.atan(0.5 * k["width"] / k["fx"]))


def envmap_key(driver) -> str:
    return driver.execute_script("const i = document.getElementById('envmap-img');"
                                 "return i.complete && i.naturalWidth ? (i.dataset.key || '') : '';")


def wait_envmap(driver, frame: int, timeout_s: float = 30) -> str:
    """Wait for the selected probe's env map of `frame` to be on screen; returns its key."""
    return wait_until(lambda: (k := envmap_key(driver)) and k.split("|")[1] == str(frame) and k, timeout_s,
                      interval_s=0.1, what=f"env map of frame {frame}")


def set_slider(driver, element_id: str, value, event: str = "input") -> None:
    driver.execute_script("""
        const s = document.getElementById(arguments[0]);
        s.value = String(arguments[1]);
        s.dispatchEvent(new Event(arguments[2], {bubbles: true}));
    """, element_id, value, event)


# ---------------------------------------------------------------------------------------
# The uploaded job (shared by the tests below)
# ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def finished_page(browser, ui_stack, switch_capture):
    """Open the page, enter the API key, upload the clip, record the progress seen on the page
    until the job has succeeded and the frame is shown."""
    from selenium.webdriver.support.ui import Select

    capture_dir, doc = switch_capture
    browser.get(ui_stack.base_url + "/")
    wait_for(browser, "return document.getElementById('key-status').textContent.includes('required')", 15,
             "the page asking for an API key")
    browser.find_element("id", "api-key").send_keys(KEY)
    browser.find_element("css selector", "#key-form button").click()
    wait_for(browser, "return document.getElementById('key-status').textContent === 'key accepted'", 15)

    browser.find_element("id", "file-input").send_keys(str(capture_dir / "video.mp4"))
    browser.find_element("id", "depth-input").send_keys(str(capture_dir / "depth.npz"))
    Select(browser.find_element("id", "temporal-input")).select_by_value("on")
    browser.find_element("id", "hfov-input").send_keys(f"{hfov_deg(doc):.6f}")
    browser.find_element("id", "upload-button").click()

    seen: list[tuple[str, str]] = []
    deadline = time.monotonic() + JOB_TIMEOUT_S
    shot_taken = False
    while time.monotonic() < deadline:
        state = browser.execute_script(
            "return [document.getElementById('job-state').dataset.state || '', "
            "document.getElementById('progress-percent').textContent];")
        if not seen or seen[-1] != tuple(state):
            seen.append(tuple(state))
        if state[0] == "running" and not shot_taken and browser.execute_script(
                "return document.getElementById('progress-iteration').textContent.includes('/')"):
            screenshot(browser, "1_progress")
            shot_taken = True
        if state[0] in ("succeeded", "failed", "cancelled"):
            break
        time.sleep(0.1)
    assert seen and seen[-1][0] == "succeeded", (seen, ui_stack.log("worker0"))
    wait_for(browser, "return !document.getElementById('result').hidden && "
                      "document.getElementById('frame-img').naturalWidth > 0", 30, "the finished job's frame")
    screenshot(browser, "2_finished")
    return {"seen": seen, "doc": doc}


def click_frame(driver, u: float, v: float) -> None:
    from selenium.webdriver.common.action_chains import ActionChains

    img = driver.find_element("id", "frame-img")
    w, h = img.size["width"], img.size["height"]
    ActionChains(driver).move_to_element_with_offset(img, u * w - w / 2, v * h - h / 2).click().perform()


def job_id(driver) -> str:
    return driver.execute_script("return document.querySelector('#jobs-list button.current').dataset.jobId")


# ---------------------------------------------------------------------------------------
# Tests
# ---------------------------------------------------------------------------------------
def test_progress_is_live_and_reaches_100_percent(finished_page, browser):
    seen = finished_page["seen"]
    percents = [int(p.split()[0]) for _, p in seen]
    assert percents[-1] == 100 and text(browser, "progress-percent") == "100 %"
    assert any(0 < p < 100 for p in percents), f"no intermediate progress was shown: {seen}"
    assert percents == sorted(percents), f"progress went backwards: {seen}"
    assert browser.find_element("id", "job-state").get_attribute("data-state") == "succeeded"
    urls = browser.execute_script("return performance.getEntriesByType('resource').map(e => e.name)")
    assert any(u.endswith("/events") for u in urls), "progress did not come from the event stream"
    # the loss curve received points from the event stream (or the artefact's curve)
    assert browser.execute_script("return document.getElementById('loss-chart').width > 0")
    assert text(browser, "progress-loss") not in ("", "—")


def test_click_places_a_probe_in_front_of_the_surface_and_shows_its_env_map(finished_page, browser, ui_stack):
    before = image_pixels(browser, "frame-img")
    click_frame(browser, *CLICK_UV)
    key = wait_envmap(browser, 0)
    probe = browser.execute_script("return document.querySelectorAll('#probe-list li[data-probe]').length")
    assert probe == 1
    env = image_pixels(browser, "envmap-img")
    assert env.shape == (128, 256, 3)
    assert env.std() > 0.01, "the env map is flat"

    # the probe sits on the clicked pixel's ray, just in front of the surface
    u, v = browser.execute_script("const li = document.querySelector('#probe-list li[data-probe]');"
                                  "return [Number(li.dataset.u), Number(li.dataset.v)]")
    assert abs(u - CLICK_UV[0]) < 0.02 and abs(v - CLICK_UV[1]) < 0.02
    with ui_stack.client() as c:
        placement = c.get(f"/lightfield/{job_id(browser)}/probe", params={"u": u, "v": v, "t": 0}).json()
    assert placement["surface_depth"] is not None
    assert 0.7 * placement["surface_depth"] < placement["default_depth"] < placement["surface_depth"]
    np.testing.assert_allclose([float(v) for v in key.split("|")[2].split(",")], placement["x"], rtol=1e-6)

    # the balls are composited into the frame around the click
    wait_for(browser, "const k = document.getElementById('frame-img').dataset.key || '';"
                      "return k.startsWith('0|') && k.split('|')[1] !== 'plain'", 30, "the frame with the balls")
    after = image_pixels(browser, "frame-img")
    h, w = after.shape[:2]
    r, c0 = int(CLICK_UV[1] * h), int(CLICK_UV[0] * w)
    window = (slice(max(r - 3, 0), r + 4), slice(max(c0 - 3, 0), c0 + 4))
    assert np.abs(after[window] - before[window]).mean() > 0.02, "no ball was drawn at the probe"
    screenshot(browser, "3_probe")


def test_time_slider_across_the_light_switch_changes_the_env_map(finished_page, browser):
    if not browser.execute_script("return document.querySelectorAll('#probe-list li[data-probe]').length"):
        click_frame(browser, *CLICK_UV)
        wait_envmap(browser, 0)
    set_slider(browser, "exposure-slider", browser.execute_script(
        "return document.getElementById('exposure-slider').value"), "change")  # freeze the exposure
    set_slider(browser, "time-slider", BEFORE_FRAME)
    wait_envmap(browser, BEFORE_FRAME)
    before = image_pixels(browser, "envmap-img")
    screenshot(browser, "4_before_switch")
    set_slider(browser, "time-slider", AFTER_FRAME)
    wait_envmap(browser, AFTER_FRAME)
    after = image_pixels(browser, "envmap-img")
    screenshot(browser, "5_after_switch")
    label = text(browser, "time-label")
    times = finished_page["doc"]["fps"]
    assert label == f"t = {AFTER_FRAME / times:.3f} s"
    assert np.abs(after - before).mean() > 0.02, "the env map did not change across the switch"
    assert after.mean() < before.mean(), "the room should be darker after the ceiling panel switched off"


def test_several_probes_can_be_selected_and_removed(finished_page, browser):
    start = browser.execute_script("return document.querySelectorAll('#probe-list li[data-probe]').length")
    click_frame(browser, 0.25, 0.6)
    wait_for(browser, "return document.querySelectorAll('#probe-list li[data-probe]').length === arguments[0]", 30,
             "a second probe", start + 1)
    wait_for(browser, "return document.querySelectorAll('.marker').length === arguments[0]", 10, "", start + 1)
    first = browser.find_element("css selector", "#probe-list li[data-probe]")
    number = first.get_attribute("data-probe")
    first.click()  # selecting re-renders the list
    selected = f"#probe-list li[data-probe='{number}']"
    wait_for(browser, "return document.querySelector(arguments[0]).classList.contains('selected')", 10,
             "the clicked probe selected", selected)
    assert browser.find_element("css selector", ".marker.selected").text == number
    browser.find_element("css selector", selected + " .remove").click()
    wait_for(browser, "return document.querySelectorAll('#probe-list li[data-probe]').length === arguments[0]", 10,
             "", start)
    assert not browser.find_elements("css selector", selected)


def test_downloaded_exr_parses_and_matches_the_api(finished_page, browser, downloads, ui_stack):
    from core.io.exr import read_exr

    if not browser.execute_script("return document.querySelectorAll('#probe-list li[data-probe]').length"):
        click_frame(browser, *CLICK_UV)
    frame = browser.execute_script("return Number(document.getElementById('time-slider').value)")
    selected = browser.execute_script("return document.querySelector('#probe-list li.selected').dataset.probe")
    key = wait_until(lambda: (k := envmap_key(browser)) and k.split("|")[:2] == [selected, str(frame)] and k, 30,
                     what="the selected probe's env map")
    for f in downloads.glob("*"):
        f.unlink()
    browser.find_element("css selector", "[data-download=exr]").click()
    exr = wait_until(lambda: [p for p in downloads.glob("*.exr")], 30, what="the EXR download")[0]
    wait_until(lambda: exr.stat().st_size > 0 and not list(downloads.glob("*.crdownload")), 10)
    hdr = read_exr(exr.read_bytes())
    assert hdr.shape == (256, 512, 3) and np.isfinite(hdr).all() and hdr.min() >= 0

    x = key.split("|")[2]
    t = frame / finished_page["doc"]["fps"]
    with ui_stack.client() as c:
        ref = c.get(f"/lightfield/{job_id(browser)}/envmap", params={"x": x, "t": t, "format": "exr", "height": 256})
    np.testing.assert_allclose(hdr, read_exr(ref.content), rtol=1e-5, atol=1e-7)
    screenshot(browser, "6_download")


def test_the_api_key_never_appears_in_a_url(finished_page, browser):
    urls = browser.execute_script("return performance.getEntriesByType('resource').map(e => e.name)")
    urls.append(browser.current_url)
    assert urls and not [u for u in urls if KEY in u]
    assert browser.execute_script("return sessionStorage.getItem('lightfield.apiKey')") == KEY
    errors = [e for e in browser.get_log("browser") if e["level"] == "SEVERE" and "401" not in e["message"]]
    assert not errors, errors


def test_a_bad_upload_shows_the_services_message(finished_page, browser, tmp_path):
    bogus = tmp_path / "notes.txt"
    bogus.write_text("not a picture")
    browser.find_element("id", "file-input").send_keys(str(bogus))
    browser.find_element("id", "upload-button").click()
    wait_for(browser, "return !document.getElementById('upload-error').hidden", 30, "the upload error")
    assert "not an image, a video" in text(browser, "upload-error")
    assert not browser.find_element("id", "result").get_attribute("hidden"), "the open job was closed"
    screenshot(browser, "7_bad_upload")


def test_the_page_shows_the_fov_and_depth_it_used_and_re_estimates_with_a_corrected_fov(
    finished_page, browser, ui_stack
):
    """Runs last: it submits a second job. The camera panel says which FOV and depth the light
    field was estimated with; "Re-estimate" sends the same file with the corrected FOV."""
    import httpx

    doc = finished_page["doc"]
    wait_for(browser, "return document.getElementById('fov-value').textContent.includes('°')", 15, "the FOV")
    assert text(browser, "fov-value") == f"{hfov_deg(doc):.1f}°"
    assert "params" in text(browser, "fov-source")
    assert "file:" in text(browser, "depth-source")
    assert text(browser, "exposure-source").startswith("locked")  # a static camera, no exposures given
    assert text(browser, "grade-info").split(" · ")[0] in ("explained", "partly explained", "worse than a constant map")
    assert "seen" in text(browser, "grade-info") and "filled" in text(browser, "grade-info")
    before = job_id(browser)
    field = browser.find_element("id", "fov-correct")
    field.clear()
    field.send_keys("72.5")
    browser.find_element("id", "fov-button").click()
    wait_for(browser, "return document.querySelector('#jobs-list button.current') && "
                      f"document.querySelector('#jobs-list button.current').dataset.jobId !== '{before}'", 30,
             "the re-estimate job")
    after = job_id(browser)
    with httpx.Client(base_url=ui_stack.base_url, headers={"Authorization": f"Bearer {KEY}"}) as c:
        params = c.get(f"/jobs/{after}").json()["params"]
        assert params["intrinsics"] == {"fx": None, "fy": None, "cx": None, "cy": None, "hfov_deg": 72.5} \
            or params["intrinsics"].get("hfov_deg") == 72.5
        assert params["temporal"] == "on"  # the rest of the first job's parameters is kept
        c.delete(f"/jobs/{after}")
