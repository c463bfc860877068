"""The pages a researcher opens, loaded in headless Chromium: the MLflow runs page shows the
study's nested cell runs, a cell's page shows its success metric and its logged model, the
dashboard lists the sweep, and the report's figures load. With ACRMDN_SCREENSHOTS set, each
page is also saved as a PNG there (docs/screenshots, shown in docs/usage.md and docs/testing.md)."""

from __future__ import annotations

import json
import time
import urllib.request
from pathlib import Path

import pytest

pytest.importorskip("selenium")
from selenium.common.exceptions import NoSuchElementException  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import WebDriverWait  # noqa: E402

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(1800)]
WAIT = 120  # s: a cold MLflow UI on 2 busy cores takes tens of seconds to render


def rest(base: str, path: str, body: dict | None = None) -> dict:
    """The MLflow or dashboard REST API (what the pages show, read without a client library)."""
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(base + path, data=data, headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=30) as r:
        return json.load(r)


def _body(driver) -> str:
    return driver.find_element(By.TAG_NAME, "body").text


def _wait_for_text(driver, *texts: str) -> None:
    try:
        WebDriverWait(driver, WAIT).until(lambda d: all(t in _body(d) for t in texts))
    except Exception as exc:
        missing = [t for t in texts if t not in _body(driver)]
        raise AssertionError(f"{driver.current_url}: not shown after {WAIT}s: {missing}") from exc


def _close_assistant(driver) -> None:
    """MLflow 3 opens an assistant panel beside the page; close it for a readable picture."""
    for button in driver.find_elements(By.CSS_SELECTOR, "button[aria-label='Close']"):
        if button.is_displayed():
            button.click()
            time.sleep(0.5)
            return


def _shot(driver, screenshots: Path | None, name: str) -> None:
    if screenshots is not None:
        time.sleep(1.0)  # let charts finish their transitions
        driver.save_screenshot(str(screenshots / name))


def _study_runs(mlflow_ui: str) -> tuple[str, dict, list[dict]]:
    exp = rest(mlflow_ui, "/api/2.0/mlflow/experiments/get-by-name?experiment_name=ablation")["experiment"]
    runs = rest(mlflow_ui, "/api/2.0/mlflow/runs/search", {"experiment_ids": [exp["experiment_id"]]})["runs"]
    tags = [{t["key"]: t["value"] for t in r["data"].get("tags", [])} for r in runs]
    (parent,) = [r for r, t in zip(runs, tags, strict=True) if "mlflow.parentRunId" not in t]
    children = [r for r, t in zip(runs, tags, strict=True) if t.get("mlflow.parentRunId") == parent["info"]["run_id"]]
    assert len(children) == 2, [r["info"]["run_name"] for r in runs]
    return exp["experiment_id"], parent, children


def test_mlflow_runs_page_shows_the_nested_cells(driver, mlflow_ui, screenshots):
    exp_id, parent, children = _study_runs(mlflow_ui)
    driver.get(f"{mlflow_ui}/#/experiments/{exp_id}/runs")
    _wait_for_text(driver, parent["info"]["run_name"])
    _close_assistant(driver)
    names = [c["info"]["run_name"] for c in children]
    if not all(n in _body(driver) for n in names):  # collapsed: open the parent's row
        link = driver.find_element(By.LINK_TEXT, parent["info"]["run_name"])
        row = link.find_element(By.XPATH, "./ancestor::*[@role='row'][1]")
        try:
            row.find_element(By.CSS_SELECTOR, "button[data-component-id*='runnamecellrenderer']").click()
        except NoSuchElementException as exc:
            raise AssertionError("the study's run has no control to show its nested runs") from exc
    _wait_for_text(driver, *names)
    _shot(driver, screenshots, "mlflow-runs.png")


def test_a_cells_page_shows_its_success_metric_and_its_model(driver, mlflow_ui, screenshots):
    exp_id, _, children = _study_runs(mlflow_ui)
    cell = children[0]
    success = sorted(m["key"] for m in cell["data"]["metrics"] if "success_rate" in m["key"])
    assert success, [m["key"] for m in cell["data"]["metrics"]]
    driver.get(f"{mlflow_ui}/#/experiments/{exp_id}/runs/{cell['info']['run_id']}")
    _wait_for_text(driver, cell["info"]["run_name"], *success)

    (output,) = cell["outputs"]["model_outputs"]
    driver.get(f"{mlflow_ui}/#/experiments/{exp_id}/models/{output['model_id']}")
    _wait_for_text(driver, output["model_id"], cell["info"]["run_name"], "Ready")
    _close_assistant(driver)
    _shot(driver, screenshots, "mlflow-model.png")


def test_dashboard_lists_the_sweep(driver, dashboard, screenshots):
    (study,) = rest(dashboard, "/api/studies")["study_summaries"]
    driver.get(f"{dashboard}/dashboard")
    _wait_for_text(driver, study["study_name"])
    driver.get(f"{dashboard}/dashboard/studies/{study['study_id']}")
    _wait_for_text(driver, study["study_name"], "History")
    _shot(driver, screenshots, "optuna-dashboard.png")


def test_report_figures_load(driver, store, screenshots):
    index = store / "reports" / "out" / "smoke" / "index.html"
    assert index.is_file(), sorted(str(p.relative_to(store)) for p in store.rglob("index.html"))
    driver.get(index.as_uri())
    WebDriverWait(driver, WAIT).until(lambda d: d.execute_script("return document.readyState") == "complete")
    images = driver.execute_script(
        "return Array.from(document.images).map(i => [i.getAttribute('src'), i.complete && i.naturalWidth > 0])")
    assert len(images) >= 3, images  # success bars, compute time, training time at least
    assert [src for src, ok in images if not ok] == [], "figures that did not load"
    _shot(driver, screenshots, "report.png")
