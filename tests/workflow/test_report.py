"""`snakemake --report` after the corridor run: what the report file holds, and what a
browser (headless Chromium) displays of it."""

from __future__ import annotations

import base64
import re
import time
from pathlib import Path

import pytest
from workflow_helpers import in_ci, repo_config

pytestmark = [pytest.mark.workflow, pytest.mark.data]

CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"


def embedded(report: Path, name: str) -> list[bytes]:
    """The files named ``name`` that the report embeds (as base64 data URIs)."""
    text = report.read_text()
    found = re.findall(rf"filename={re.escape(name)};base64,([A-Za-z0-9+/=]+)", text)
    return [base64.b64decode(data) for data in found]


def test_report_holds_the_table_the_curve_and_the_montages(corridor_run):
    workdir, report = corridor_run
    results = workdir / "results"
    table = embedded(report, "recall_corridor.csv")
    assert table and table[0] == (results / "recall_corridor.csv").read_bytes()
    assert b"recall@1" in table[0] and b"segvlad" in table[0]
    curve = embedded(report, "recall_corridor.png")
    assert curve and curve[0] == (results / "plots" / "recall_corridor.png").read_bytes()
    # One retrieval montage per method, SegVLAD's segment matches; the files are named
    # by method inside per-figure folders, so compare them as the report embeds them.
    montages = sorted((results / "figures" / "corridor" / "retrievals").glob("*.png"))
    matches = sorted((results / "figures" / "corridor" / "segment_matches").glob("*.png"))
    # Each re-ranked row (method+reranker) has its own montage, re-ranked beside retrieved.
    corridor = repo_config()["datasets"]["corridor"]
    rows = len(corridor["methods"]) + sum(len(r) for r in corridor["rerank"].values())
    assert rows > len(corridor["methods"])
    assert len(montages) == rows and len(matches) == 4
    text = report.read_text()
    for png in (montages[0], matches[0]):
        data = base64.b64encode(png.read_bytes()).decode()
        assert data in text, png
    # Captions are rendered with the run's values, and the results are grouped by dataset.
    assert "Queries without any positive are left out" in text
    assert "corridor" in text and "Retrievals" in text


def chrome():
    """A headless Chromium driven by Selenium; skipped when missing (a failure in CI,
    where .ci/run installs Debian's chromium and chromium-driver)."""
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        webdriver = None
    missing = webdriver is None or not (Path(CHROMIUM).exists() and Path(CHROMEDRIVER).exists())
    if missing:
        message = "headless Chromium needs selenium, /usr/bin/chromium and chromedriver"
        if in_ci():
            pytest.fail(message, pytrace=False)
        pytest.skip(message)
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    # No network here: background services would only fail to connect.
    for flag in (
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--window-size=1400,1000",
    ):
        options.add_argument(flag)
    return webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)


def click_link(driver, text: str, timeout: float = 20.0) -> None:
    from selenium.webdriver.common.by import By

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for link in driver.find_elements(By.TAG_NAME, "a"):
            if link.text.strip() == text and link.is_displayed():
                link.click()
                return
        time.sleep(0.2)
    raise AssertionError(f"no link {text!r} in the report page")


def test_chromium_displays_the_recall_curve(corridor_run, tmp_path):
    from selenium.webdriver.common.by import By

    _, report = corridor_run
    driver = chrome()
    try:
        driver.get(report.resolve().as_uri())
        click_link(driver, "Results")
        click_link(driver, "corridor")
        click_link(driver, "Recall")
        deadline = time.monotonic() + 20
        while not driver.find_elements(By.XPATH, "//td[text()='Recall@N curves']"):
            assert time.monotonic() < deadline, "the Recall list shows no Recall@N curves"
            time.sleep(0.2)
        row = driver.find_element(By.XPATH, "//td[text()='Recall@N curves']/..")
        row.find_element(By.CSS_SELECTOR, "a[iconname='eye']").click()
        curve = None
        while curve is None and time.monotonic() < deadline:
            for image in driver.find_elements(By.TAG_NAME, "img"):
                if "filename=recall_corridor.png" in (image.get_attribute("src") or ""):
                    curve = image
            time.sleep(0.2)
        assert curve is not None, "the recall curve image is not in the page"
        # Displayed, decoded (natural size of the PNG) and drawn at a readable size.
        loaded = driver.execute_script(
            "return arguments[0].complete && arguments[0].naturalWidth", curve
        )
        assert curve.is_displayed() and loaded > 300
        assert curve.size["width"] > 300 and curve.size["height"] > 200
        driver.save_screenshot(str(tmp_path / "report.png"))
    finally:
        driver.quit()
    assert (tmp_path / "report.png").stat().st_size > 0
