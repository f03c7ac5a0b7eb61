"""``depthnerf app`` in a real headless browser: Debian's Chromium driven by selenium through its chromedriver.

The app runs in a subprocess on a free localhost port (2 orbit views by default and a 24-sample mesh to stay quick;
the app's default 64-sample mesh when it writes the screenshot). One
tab uploads a non-image file and a photo on a cluttered background (one-line messages, the RGBA hint), then a
bundled example and reconstructs it while a second tab picks the other example from the page's list, asks for
its reconstruction and must show its queue position; then the orbit video (a real MP4), the GIF, the 3D viewer and the three downloads must be on the page.
A screenshot goes to ``tmp_path/app.png``; with ``DEPTHNERF_APP_SCREENSHOT=docs/figures/app.png`` it is also
copied there (how README's figure is made). Then a new (bad) upload must clear every earlier output, and the
depth prior's line must name the weights Depth Anything loads and their licence. Last, SIGTERM stops the server
with exit status 0, its temporary run folder removed and Gradio's cached uploads and outputs deleted.

Nothing downloads a browser: the driver and browser paths are given explicitly (``DEPTHNERF_CHROMEDRIVER``,
``DEPTHNERF_CHROMIUM``, default ``/usr/bin/chromedriver`` and ``/usr/bin/chromium``) and Selenium Manager is
pointed at a missing file, so any attempt to fetch one fails. Skipped, with the reason, when gradio, selenium or
the browser is missing.
"""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = os.environ.get("DEPTHNERF_CHROMIUM", "/usr/bin/chromium")
CHROMEDRIVER = os.environ.get("DEPTHNERF_CHROMEDRIVER", "/usr/bin/chromedriver")
EXAMPLES = ROOT / "depthnerf" / "app" / "examples"

pytest.importorskip("gradio", reason="gradio is not installed (pip install -e '.[app]')")
pytest.importorskip("selenium", reason="selenium is not installed (pip install -e '.[dev]')")
if not (Path(CHROMIUM).is_file() and Path(CHROMEDRIVER).is_file()):
    pytest.skip(f"no Chromium at {CHROMIUM} with its driver at {CHROMEDRIVER} (apt-get install chromium "
                "chromium-driver)", allow_module_level=True)

from selenium import webdriver  # noqa: E402
from selenium.webdriver.chrome.options import Options  # noqa: E402
from selenium.webdriver.chrome.service import Service  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.common.keys import Keys  # noqa: E402

pytestmark = pytest.mark.slow


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("app_server")
    port = free_port()
    (tmp / "tmp").mkdir()
    env = {**os.environ, "GRADIO_ANALYTICS_ENABLED": "False", "GRADIO_TEMP_DIR": str(tmp / "gradio"),
           "TMPDIR": str(tmp / "tmp"), "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    log = open(tmp / "server.log", "w")  # noqa: SIM115 - closed below
    mesh = "64" if os.environ.get("DEPTHNERF_APP_SCREENSHOT") else "24"  # the screenshot shows the app's default
    proc = subprocess.Popen([sys.executable, "-m", "depthnerf", "app", "--port", str(port), "--views", "2",
                             "--mesh-resolution", mesh], stdout=log, stderr=subprocess.STDOUT, env=env, cwd=tmp)
    url = f"http://127.0.0.1:{port}/"
    deadline = time.monotonic() + 180
    while True:
        try:
            with urllib.request.urlopen(url, timeout=5) as resp:
                if resp.status == 200:
                    break
        except OSError:
            pass
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            pytest.fail(f"the app did not start: {(tmp / 'server.log').read_text()[-2000:]}")
        time.sleep(0.5)
    yield url, tmp / "server.log", proc, tmp
    proc.terminate()
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
    log.close()


@pytest.fixture(scope="module")
def browser(server):
    old = {k: os.environ.get(k) for k in ("SE_MANAGER_PATH", "SE_OFFLINE")}
    os.environ["SE_MANAGER_PATH"] = "/nonexistent/selenium-manager-is-disabled"
    os.environ["SE_OFFLINE"] = "true"
    opts = Options()
    opts.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1400,1800",
                "--enable-unsafe-swiftshader", "--disable-gpu-sandbox", "--no-first-run"):
        opts.add_argument(arg)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)
    yield driver
    driver.quit()
    for key, value in old.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value


def wait_for(condition, timeout: float, what: str, poll: float = 0.25):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            value = condition()
        except Exception:  # noqa: BLE001 - elements come and go while Svelte re-renders
            value = None
        if value:
            return value
        time.sleep(poll)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def status(driver) -> str:
    return driver.find_element(By.CSS_SELECTOR, "#status textarea").get_attribute("value") or ""


def upload(driver, path: Path) -> None:
    """Clear the upload box if it holds a file, then upload ``path``."""
    for button in driver.find_elements(By.CSS_SELECTOR, "#upload button[aria-label='Clear']"):
        button.click()
    field = wait_for(lambda: driver.find_elements(By.CSS_SELECTOR, "#upload input[type=file]"), 20, "the upload field")
    field[0].send_keys(str(path))


def fetch(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=30) as resp:
        return resp.read()


def test_page_in_headless_chromium(server, browser, tmp_path):
    url, log, _, _ = server
    d = browser
    d.get(url)
    wait_for(lambda: d.find_elements(By.CSS_SELECTOR, "#upload input[type=file]"), 60, "the page")
    assert wait_for(lambda: d.find_element(By.CSS_SELECTOR, "#status textarea").is_displayed(), 30, "the status box")
    assert d.find_element(By.CSS_SELECTOR, "#facing-auto input[type=checkbox]").is_selected()  # the car's facing head

    # bad input: a non-image file, then a photo on a cluttered background -> one line each, the RGBA hint
    notes = tmp_path / "notes.png"
    notes.write_text("not pixels\n")
    upload(d, notes)
    msg = wait_for(lambda: status(d).startswith("error") and status(d), 60, "the non-image message")
    assert msg.startswith("error: notes.png: not an image") and "\n" not in msg
    rng = np.random.default_rng(0)
    scene = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
    scene[40:80, 50:110] = (200, 30, 30)
    Image.fromarray(scene).save(tmp_path / "scene.png")
    upload(d, tmp_path / "scene.png")
    msg = wait_for(lambda: "scene.png" in status(d) and status(d), 60, "the cluttered-background message")
    assert msg.startswith("error: scene.png: the background is not a plain colour") and "RGBA" in msg
    assert wait_for(lambda: d.find_element(By.ID, "clutter-hint").is_displayed(), 10, "the RGBA hint")
    assert "Traceback" not in d.find_element(By.TAG_NAME, "body").text

    # the example, with a second tab queued behind it
    upload(d, EXAMPLES / "car_rgba.png")
    wait_for(lambda: status(d).startswith("ready: car_rgba.png"), 60, "the preprocessed example")
    assert not any(e.is_displayed() for e in d.find_elements(By.ID, "clutter-hint"))  # hidden = not in the DOM
    tab_a = d.current_window_handle
    d.switch_to.new_window("tab")
    tab_b = d.current_window_handle
    d.get(url)
    wait_for(lambda: d.find_elements(By.CSS_SELECTOR, "#upload input[type=file]"), 60, "the second tab")
    example = "//button[.//*[contains(@class, 'gallery') and contains(text(), 'chair_white.png')]]"
    d.find_element(By.XPATH, example).click()  # the second tab picks the bundled example instead of uploading
    wait_for(lambda: status(d).startswith("ready: chair_white.png"), 60, "the second tab's example")
    d.switch_to.window(tab_a)
    views = d.find_element(By.CSS_SELECTOR, "#views input[type=number]")  # more views: tab B surely waits
    views.clear()
    views.send_keys("5", Keys.TAB)
    wait_for(lambda: d.find_element(By.CSS_SELECTOR, "#views input[type=range]").get_attribute("value") == "5", 10,
             "the views slider at 5")
    d.find_element(By.ID, "run").click()
    d.switch_to.window(tab_b)
    d.find_element(By.ID, "run").click()
    queued = wait_for(lambda: re.search(r"queue: ?\d+/\d+", d.find_element(By.TAG_NAME, "body").text), 60,
                      "the second tab's queue position")
    assert queued.group(0)
    wait_for(lambda: status(d).startswith(("done", "error")), 180, "the second tab's result")
    assert status(d).startswith("done in "), status(d)
    d.switch_to.window(tab_b)
    d.close()
    d.switch_to.window(tab_a)
    wait_for(lambda: status(d).startswith(("done", "error")), 180, "the first tab's result")
    assert status(d).startswith("done in ") and "5 views" in status(d), status(d)

    # outputs: video (an MP4), GIF, prepared input, depth prior, 3D viewer, three downloads
    video = wait_for(lambda: d.find_element(By.CSS_SELECTOR, "#video video").get_attribute("src"), 30, "the video")
    assert video.endswith("turntable.mp4") and fetch(video)[4:8] == b"ftyp"
    for elem_id, name in (("gif", "turntable.gif"), ("prepared", ""), ("prior-image", "depth_prior.png")):
        src = wait_for(lambda e=elem_id: d.find_element(By.CSS_SELECTOR, f"#{e} img").get_attribute("src"), 30,
                       elem_id)
        assert src.startswith("http") and src.endswith(name) and len(fetch(src)) > 100, (elem_id, src)
    assert wait_for(lambda: d.find_elements(By.CSS_SELECTOR, "#viewer canvas"), 30, "the 3D viewer canvas")
    glb = d.find_element(By.CSS_SELECTOR, "#viewer a[data-testid='model3d-download-link']").get_attribute("href")
    assert glb.endswith("mesh.glb") and fetch(glb)[:4] == b"glTF"
    links = {a.get_attribute("href").rsplit("/", 1)[-1]: a.get_attribute("href")
             for a in d.find_elements(By.CSS_SELECTOR, "#downloads a[href]")}
    assert {"mesh.glb", "mesh.ply", "points.ply"} <= set(links), links
    assert fetch(links["mesh.glb"])[:4] == b"glTF" and fetch(links["points.ply"]).startswith(b"ply")
    assert "Traceback" not in log.read_text()
    assert wait_for(lambda: "--facing auto: the checkpoint's facing head" in d.find_element(By.ID, "details").text,
                    30, "the details naming the facing head")

    # screenshot of the whole page
    for _ in range(2):  # the layout settles after a resize
        height = d.execute_script("return document.documentElement.scrollHeight")
        d.set_window_size(1400, min(max(height + 150, 1200), 4000))
        time.sleep(1.5)  # let the viewer draw at the new size
    shot = tmp_path / "app.png"
    d.save_screenshot(str(shot))
    assert Image.open(shot).size[0] >= 1000
    if target := os.environ.get("DEPTHNERF_APP_SCREENSHOT"):
        shutil.copyfile(shot, target)

    # a new upload (here a bad one) clears every earlier output
    upload(d, notes)
    wait_for(lambda: status(d).startswith("error: notes.png"), 60, "the new upload's message")
    for selector in ("#video video", "#gif img", "#prior-image img", "#prepared img", "#viewer canvas",
                     "#downloads a[href]"):
        assert wait_for(lambda sel=selector: not d.find_elements(By.CSS_SELECTOR, sel), 20, f"{selector} cleared")
    # the depth prior names the weights it loads and their licence; no command-line flags on the page
    assert "MIT" in d.find_element(By.ID, "prior-info").text
    d.find_element(By.XPATH, "//*[@id='prior']//label[contains(., 'Depth Anything V2')]").click()
    info = wait_for(lambda: "Base" in d.find_element(By.ID, "prior-info").text and
                    d.find_element(By.ID, "prior-info").text, 20, "the Depth Anything line")
    assert "Depth-Anything-V2-Base-hf" in info and "CC-BY-NC-4.0" in info
    body = d.find_element(By.TAG_NAME, "body").text
    assert not re.findall(r"--(?:mask|depth-checkpoint|background-model|fill)\b", body), body
    checked = d.find_element(By.CSS_SELECTOR, "#remove-bg input[type=checkbox]").is_selected()
    assert checked == all(importlib.util.find_spec(m) is not None for m in ("rembg", "onnxruntime"))


def test_sigterm_stops_the_server_and_removes_its_files(server):
    _, log, proc, tmp = server
    proc.terminate()
    assert proc.wait(timeout=60) == 0, log.read_text()[-2000:]
    work = re.search(r"runs are written to (\S+)\)", log.read_text())
    assert work and Path(work.group(1)).parent == tmp / "tmp" and not Path(work.group(1)).exists()
    assert any((tmp / "gradio").iterdir())  # Gradio did cache the uploads and outputs ...
    cached = [p for p in (tmp / "gradio").rglob("*") if p.is_file() and p.stat().st_size > 0]
    assert not cached, cached  # ... and deleted them (it leaves its empty upload staging files and folders)
