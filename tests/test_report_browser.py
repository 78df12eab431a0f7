"""The report in a real headless browser (Debian's chromium, driven by chromedriver through selenium).

The page must load with no console error, draw something (the screenshot of the
view is not blank), and redraw the body when the frame slider is moved. Runs
wherever a chromium binary exists (CI installs ``chromium`` and
``chromium-driver``); the screenshots' paths are printed.
"""

import io
import shutil
import time

import numpy as np
import pytest

from skelid.report import write_report
from tests.test_report import ODD, odd_result

CHROMIUM = next((p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if p), None)
pytestmark = [pytest.mark.browser, pytest.mark.skipif(
    CHROMIUM is None, reason="no chromium binary (CI installs it: apt-get install -y chromium chromium-driver)")]

#: seconds to wait for the page to draw (a loaded machine parses the 4.8 MB plotly bundle slowly)
WAIT = 120.0


@pytest.fixture(scope="module")
def browser():
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is in the test extra")
    from selenium.webdriver.chrome.service import Service

    driver_path = shutil.which("chromedriver")
    assert driver_path, "chromium is installed but chromedriver is not: apt-get install -y chromium-driver"
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1200,1000",
                "--enable-unsafe-swiftshader", "--use-angle=swiftshader", "--disable-gpu-sandbox"):
        opts.add_argument(arg)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(driver_path), options=opts)
    driver.set_page_load_timeout(WAIT)
    yield driver
    driver.quit()


def _wait(driver, script: str, what: str):
    t0 = time.monotonic()
    while time.monotonic() - t0 < WAIT:
        if driver.execute_script(script):
            return
        time.sleep(0.2)
    raise AssertionError(f"the page did not {what} within {WAIT:g} s")


def _load(driver, path):
    driver.get_log("browser")  # drop what an earlier page logged
    driver.get(path.resolve().as_uri())
    _wait(driver, "var g = document.getElementById('skeleton-view'); return g && g.dataset.ready === '1';",
          "draw the fitted body")
    driver.execute_script("document.getElementById('skeleton-view').scrollIntoView();")
    time.sleep(0.5)


def _errors(driver) -> list:
    return [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]


def _shot(driver, path, capsys):
    png = driver.find_element("id", "skeleton-view").screenshot_as_png
    path.write_bytes(png)
    with capsys.disabled():  # shown in the test output, not captured
        print(f"\nscreenshot of the report's view: {path}")
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("L"), float)


def _positions(driver, trace: int) -> list:
    return driver.execute_script(
        "var t = document.getElementById('skeleton-view')._fullData[arguments[0]];"
        "return [t.x, t.y, t.z || []];", trace)


def _move_slider(driver, fraction: float):
    """Click the slider's rail at ``fraction`` of its length, as a user would."""
    from selenium.webdriver.common.action_chains import ActionChains

    rail = driver.find_element("css selector", "#skeleton-view .slider-rail-touch-rect")
    width = rail.size["width"]
    ActionChains(driver).move_to_element_with_offset(rail, int((fraction - 0.5) * width), 0).click().perform()


def _check_view(driver, tmp_path, label: str, capsys):
    assert _errors(driver) == []
    before = _shot(driver, tmp_path / f"{label}-first-frame.png", capsys)
    assert before.std() > 5.0 and (before < 200).mean() > 0.005, "the view is blank"
    frame0 = driver.execute_script("return document.getElementById('skeleton-view').dataset.frame;")
    joints0 = _positions(driver, 4)
    _move_slider(driver, 0.7)
    _wait(driver, f"return document.getElementById('skeleton-view').dataset.frame !== '{frame0}';",
          "change frame when the slider moved")
    time.sleep(0.5)
    joints1 = _positions(driver, 4)
    assert len(joints1[0]) == len(joints0[0]) and joints1 != joints0  # the joint centres moved
    after = _shot(driver, tmp_path / f"{label}-later-frame.png", capsys)
    assert after.shape == before.shape and np.abs(after - before).mean() > 0.05  # and were drawn again
    assert _errors(driver) == []
    return int(driver.execute_script("return document.getElementById('skeleton-view').dataset.frame;"))


def test_3d_view_in_a_browser(browser, tmp_path, capsys):
    path, _ = write_report(odd_result(tmp_path / "odd"), tmp_path / "odd.html")
    _load(browser, path)
    frame = _check_view(browser, tmp_path, "3d", capsys)
    assert 40 <= frame <= 80  # 70 % along 90 frames
    # odd names are shown as written and ran nothing (an alert would have stopped the driver)
    body = browser.execute_script("return document.body.innerText;")
    assert all(n in body for n in [*ODD["marker"], ODD["parameter"]])
    assert browser.execute_script("return document.getElementById('skeleton-view')._fullLayout.scene !== undefined;")


def _planar_result(d):
    """The seed's planar arm fitted by a method that estimates no poses (the report fits them for the view)."""
    from skelid.simulate import builtin_model, simulate
    from tests.test_report import write_legacy

    model = builtin_model("case-a")
    trial = simulate(model, n_frames=120, sigma=5.0, rng=np.random.default_rng(2))
    est = {n: {"map": float(v), "mean": float(v), "sd": 2.0, "ci95": [float(v) - 4, float(v) + 4]}
           for n, v in zip(model.parameter_names, trial.theta, strict=True)}
    result = {"model": model.name, "data": "arm.trc", "units": model.units, "frames_total": 120,
              "methods": {"paper": est}, "model_description": model.to_dict()}
    return write_legacy(d, result, {"markers": trial.data.positions, "marker_names": np.array(model.marker_names),
                                    "rate": np.array(100.0), "units": np.array(model.units)})


def test_planar_view_in_a_browser(browser, tmp_path, capsys):
    path, _ = write_report(_planar_result(tmp_path / "planar"), tmp_path / "planar.html")
    _load(browser, path)
    _check_view(browser, tmp_path, "2d", capsys)
    assert browser.execute_script("return document.getElementById('skeleton-view')._fullData[0].type;") == "scatter"
