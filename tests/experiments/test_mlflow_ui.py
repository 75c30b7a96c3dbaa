"""The MLflow UI as a user sees it: `mlflow ui` on 127.0.0.1 over the smoke run's store, opened in headless
Chromium (selenium + chromedriver). The deepword experiment opening on its runs table with the run's
dataset, the parent run with its stage child runs, its tags and eval.* metrics, and the evaluate run's
report artifact must be on screen."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from tests.experiments.pipeline_runs import MlflowServer

pytestmark = pytest.mark.slow

STAGES = ("data", "priors", "relation", "detector", "export", "evaluate")
CHROMIUM = [p for p in ("/usr/bin/chromium", shutil.which("chromium"), shutil.which("google-chrome")) if p]
# Flags for a sandboxless container with no network beyond loopback (no background fetches).
FLAGS = ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--window-size=1600,1000"]


@pytest.fixture()
def browser(ui, tmp_path):
    """Headless Chromium, started while the ``ui`` server boots; yielded once the UI answers."""
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    driver_path = shutil.which("chromedriver")
    if not CHROMIUM or not driver_path:
        pytest.fail("chromium and chromedriver are needed (.ci/run installs them: apt-get install chromium chromium-driver)")
    options = Options()
    options.binary_location = CHROMIUM[0]
    for flag in [*FLAGS, f"--user-data-dir={tmp_path / 'chromium-profile'}"]:
        options.add_argument(flag)
    driver = webdriver.Chrome(options=options, service=Service(driver_path))
    driver.set_page_load_timeout(60)
    try:
        ui.wait_ready()
        yield driver
    finally:
        driver.quit()


@pytest.fixture()
def ui(smoke_store, tmp_path):
    """``mlflow ui`` over the smoke store, started, not yet answering (``browser`` waits for it)."""
    srv = MlflowServer(tmp_path, command="ui", backend_uri=smoke_store["uri"])
    try:
        yield srv
    finally:
        srv.stop()


def _page_shows(driver, texts: list[str], timeout: float = 60) -> str:
    """Wait until the page's visible text holds every one of ``texts``; return that text."""
    from selenium.common.exceptions import TimeoutException
    from selenium.webdriver.support.ui import WebDriverWait

    seen = {"text": ""}

    def ready(d):
        seen["text"] = d.find_element("tag name", "body").text
        return all(t in seen["text"] for t in texts)

    try:
        WebDriverWait(driver, timeout, poll_frequency=0.5).until(ready)
    except TimeoutException:
        missing = [t for t in texts if t not in seen["text"]]
        pytest.fail(f"not shown after {timeout} s: {missing}\n--- page text ---\n{seen['text'][:3000]}")
    return seen["text"]


def test_ui_shows_experiment_parent_run_children_tags_metrics_and_report(smoke_store, ui, browser, tmp_path):
    from mlflow.tracking import MlflowClient

    client = MlflowClient(smoke_store["uri"])
    exp = client.get_experiment_by_name("deepword")
    runs = client.search_runs([exp.experiment_id])
    (parent,) = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    evaluate = next(r for r in runs if r.info.run_name == "evaluate")
    base = f"{ui.uri}/#/experiments/{exp.experiment_id}"

    # The experiment's landing page (no /runs in the address) is its runs table, not MLflow 3's GenAI
    # overview, and the Dataset column names the run's dataset.
    browser.get(base)
    _page_shows(browser, ["deepword", "Run Name", "Dataset", "synword", parent.info.run_name[:12]])
    assert "/runs" in browser.current_url and "traces" not in browser.current_url
    browser.save_screenshot(str(tmp_path / "experiment.png"))

    browser.get(f"{base}/runs/{parent.info.run_id}")
    text = _page_shows(browser, ["Child runs", *STAGES, "profile", "smoke", "seed", "git_commit",
                                 "eval.gt.deepword.mixed.wheel_acc", "eval.gt.logic.hard.wheel_acc"])
    assert parent.info.run_name.split()[0] == "smoke" and "relation/backbone=" in parent.info.run_name
    assert parent.info.run_name.split("\n")[0][:20] in text
    shot = tmp_path / "parent_run.png"
    browser.save_screenshot(str(shot))
    assert shot.stat().st_size > 20_000

    browser.get(f"{base}/runs/{evaluate.info.run_id}/artifacts")
    _page_shows(browser, ["report.md", "report.json"])
    browser.save_screenshot(str(tmp_path / "evaluate_artifacts.png"))
    keep = Path(__file__).resolve().parents[2] / "outputs" / "ui_screenshots"
    keep.mkdir(parents=True, exist_ok=True)
    for png in tmp_path.glob("*.png"):
        shutil.copy(png, keep / png.name)
