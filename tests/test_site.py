"""The leaderboard's web site (``crowdbench leaderboard --site DIR``, crowdbench/leaderboard/site.py):
rendered from the results on disk, submission text escaped, figures cached by fingerprint, and driven
in headless Chromium (selenium): the numbers of results.json, sorting by a header click, an entry page,
nothing fetched from the network. The browser test needs chromium and chromedriver (tests/conftest.py)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest
from conftest import require_system
from PIL import Image
from test_leaderboard import FAST, MLP, add_straight, toy_checkpoint, write_yaml

from crowdbench.leaderboard import run
from crowdbench.leaderboard.render import label, table_cell
from crowdbench.leaderboard.site import training_command

CHROMIUM, CHROMEDRIVER = shutil.which("chromium"), shutil.which("chromedriver")
HOSTILE = "ORCA <script>alert(1)</script> & \"q\""


@pytest.fixture(scope="module")
def board(tmp_path_factory):
    """A scratch leaderboard (straight, ORCA, a tiny learned entry; 2 episodes of hotel, track v1) and its site."""
    root = tmp_path_factory.mktemp("lb")
    add_straight(root)
    write_yaml(root, "orca", f"name: orca\nkind: baseline\nentry: '{HOSTILE}'\npolicy: orca\nauthors: ['<i>me</i>']\n"
                             "link: https://gamma.cs.unc.edu/RVO2/\nnotes: \"two\\nlines <b>bold</b>\"\n")
    d = write_yaml(root, "toy", "name: toy\nkind: learned\nentry: Toy MLP\nencoder: mlp\nalgo: td3\nseed: 0\n"
                                "experiment: leaderboard\noverrides: [method=mlp_td3, 'encoder.hidden=[16]', seed=0]\n"
                                "authors: [tester]\n")
    toy_checkpoint(d / "checkpoint.pt", MLP)
    log: list[str] = []
    site = root / "site"
    assert run(root, **FAST, site=site, site_figures=1, log=log.append) == 0
    return root, site, log


def results(root: Path) -> dict[str, dict]:
    return {p.parent.name: json.loads(p.read_text()) for p in (root / "results").glob("*/results.json")}


@pytest.mark.slow
@pytest.mark.xdist_group("site_board")  # one worker builds the module fixture once
def test_site_files_escaping_and_cache(board, tmp_path):
    root, site, log = board
    index = (site / "index.html").read_text()
    assert {p.name for p in (site / "entries").iterdir()} == {"orca.html", "straight.html", "toy.html"}
    for name in ("orca", "straight", "toy"):  # a figure, a replay and a recording per entry, from the worker for toy
        manifest = json.loads((site / "media" / name / "media.json").read_text())
        assert (site / "media" / name / manifest["figure"]).stat().st_size > 1000
        assert [(site / "media" / name / e["recording"]).is_file() for e in manifest["episodes"]] == [True]
        (ep,) = manifest["episodes"]
        with Image.open(site / "media" / name / ep["replay"]) as gif:  # one frame per step of the episode
            assert gif.format == "GIF" and gif.n_frames == ep["steps"] > 1
        assert f'src="../media/{name}/{ep["replay"]}"' in (site / "entries" / f"{name}.html").read_text()
    # every track's table ranked by success: the rank column, then success (the first metric) not increasing
    summary = index.split('id="v1.summary"')[1].split("</table>")[0]
    head = re.findall(r"<th [^>]*>([^<]*)</th>", summary)
    assert head[:5] == ["#", "method", "trained on", "seeds", "success"]
    rows = [re.findall(r'<td data-sort="([^"]*)"', row) for row in summary.split("<tbody>")[1].split("</tr>")[:-1]]
    assert [float(r[0]) for r in rows] == [1, 2, 3]
    success = [float(r[4]) for r in rows]
    assert success == sorted(success, reverse=True) and success[0] > success[-1]
    # submission text is escaped everywhere: no script, no tag from a submission
    orca_page = (site / "entries" / "orca.html").read_text()
    for text in (index, orca_page):
        assert "<script>alert" not in text and "<i>me" not in text and "<b>bold" not in text
        assert "&lt;script&gt;alert(1)&lt;/script&gt; &amp; &quot;q&quot;" in text
    assert "&lt;i&gt;me&lt;/i&gt;" in orca_page and "two\nlines &lt;b&gt;bold&lt;/b&gt;" in orca_page
    # the training command as crowdbench submit records it, and the checkpoint's config
    toy_page = (site / "entries" / "toy.html").read_text()
    assert "crowdbench run experiment=leaderboard method=mlp_td3 &#x27;encoder.hidden=[16]&#x27; seed=0" in toy_page
    assert "max_humans: 40" in toy_page and "actor_squash: radial" in toy_page
    # cached: a second run regenerates no media; the tables are unchanged by the site
    readme, tracks = (root / "README.md").read_text(), (root / "TRACKS.md").read_text()
    log2: list[str] = []
    assert run(root, **FAST, site=site, site_figures=1, log=log2.append) == 0
    assert sum("site:" in m for m in log) == 3 and not any("site:" in m for m in log2)
    assert (root / "README.md").read_text() == readme and (root / "TRACKS.md").read_text() == tracks
    assert run(root, **FAST, log=log2.append) == 0 and (root / "README.md").read_text() == readme


def test_training_command():
    assert training_command({"kind": "baseline", "overrides": {"safety_margin": 0}}) is None
    assert training_command({"kind": "learned", "experiment": "leaderboard_long", "overrides": ["seed=1"]}) == \
        "crowdbench run experiment=leaderboard_long seed=1"
    assert training_command({"kind": "learned", "overrides": ["experiment=leaderboard", "x=a b"]}) == \
        "crowdbench run experiment=leaderboard 'x=a b'"


@pytest.mark.slow
@pytest.mark.xdist_group("site_board")  # one worker builds the module fixture once
def test_site_in_a_browser(board, tmp_path):
    require_system("chromium")
    require_system("chromedriver")
    from selenium import webdriver  # a dev dependency (pyproject's [dev])
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By

    root, site, _ = board
    opts = webdriver.ChromeOptions()
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1400,1000"):
        opts.add_argument(arg)
    opts.binary_location = CHROMIUM
    opts.set_capability("goog:loggingPrefs", {"performance": "ALL"})
    driver = webdriver.Chrome(options=opts, service=Service(CHROMEDRIVER))
    try:
        driver.get((site / "index.html").as_uri())
        table = driver.find_element(By.ID, "v1.success_rate")
        rows = table.find_elements(By.CSS_SELECTOR, "tbody tr")
        res = results(root)
        by_label = {label([r], escape=False): r for r in res.values()}
        shown = {}
        ranks = []
        for row in rows:
            cells = row.find_elements(By.TAG_NAME, "td")
            shown[cells[1].text] = cells[4].text
            ranks.append(cells[0].text)
        assert ranks == ["1", "2", "3"]  # ranked by success, the default order
        # the same numbers as results.json, formatted as leaderboard/README.md formats them
        assert shown == {lab: table_cell([r], "hotel", "success_rate", 3)[1] for lab, r in by_label.items()}
        assert shown["Straight to goal"] == "{:.3f} [{:.3f}, {:.3f}]".format(
            res["straight"]["scenes"]["hotel"]["success_rate"]["mean"], *res["straight"]["scenes"]["hotel"]
            ["success_rate"]["ci95"])

        def order(col: int) -> list[str]:
            return [r.find_elements(By.TAG_NAME, "td")[col].text
                    for r in table.find_elements(By.CSS_SELECTOR, "tbody tr")]

        def value(text: str) -> float:
            return float(text.split()[0])

        before = order(1)
        mean = {lab: r["scenes"]["hotel"]["success_rate"]["mean"] for lab, r in by_label.items()}
        assert before == sorted(before, key=lambda lab: -mean[lab])  # ranked: the best first
        header = table.find_elements(By.TAG_NAME, "th")[4]
        header.click()  # ascending by the numbers (a stable sort: ties keep their order)
        assert order(1) == sorted(before, key=mean.get) and header.get_attribute("aria-sort") == "ascending"
        assert [value(t) for t in order(4)] == sorted(mean.values())
        assert order(1) != before  # this board's success: 1.0, 0.5, 0.0
        header.click()
        assert order(1) == sorted(before, key=lambda lab: -mean[lab])
        assert header.get_attribute("aria-sort") == "descending"
        table.find_elements(By.TAG_NAME, "th")[1].click()  # a text column: by name
        assert order(1) == sorted(before, key=str.lower)
        # the track's summary: ranked by its headline, success the first metric, visible without scrolling
        summary = driver.find_element(By.ID, "v1.summary")
        heads = [h.text.rstrip(" ↕▲▼") for h in summary.find_elements(By.TAG_NAME, "th")]
        assert heads[:5] == ["#", "method", "trained on", "seeds", "success"]
        cells = [r.find_elements(By.TAG_NAME, "td") for r in summary.find_elements(By.CSS_SELECTOR, "tbody tr")]
        assert [c[0].text for c in cells] == ["1", "2", "3"]
        assert [value(c[4].text) for c in cells] == sorted((value(c[4].text) for c in cells), reverse=True)
        right = driver.execute_script("return arguments[0].getBoundingClientRect().right", cells[0][4])
        assert right <= driver.execute_script("return window.innerWidth")
        driver.save_screenshot(str(tmp_path / "index.png"))
        # no http(s) URL in a src or href but the submissions' own links
        refs = driver.execute_script(
            "return Array.from(document.querySelectorAll('[src],[href]')).map("
            "e => [e.getAttribute('src') || e.getAttribute('href'), e.className])")
        outside = [(u, c) for u, c in refs if re.match(r"(?i)\s*(https?:)?//", u)]
        assert outside == [("https://gamma.cs.unc.edu/RVO2/", "external")]
        # an entry link opens its page
        table.find_element(By.LINK_TEXT, "Toy MLP").click()
        assert driver.current_url.endswith("/entries/toy.html")
        assert driver.find_element(By.TAG_NAME, "h1").text == "Toy MLP"
        img = driver.find_element(By.CSS_SELECTOR, ".media img")
        assert driver.execute_script("return arguments[0].complete && arguments[0].naturalWidth", img) > 100
        replay = driver.find_element(By.CSS_SELECTOR, ".media .replay img")  # the episode plays in the page
        assert replay.get_attribute("src").endswith(".gif")
        assert driver.execute_script("return arguments[0].complete && arguments[0].naturalWidth", replay) > 100
        links = [a.get_attribute("href") for a in driver.find_elements(By.CSS_SELECTOR, ".media a[download]")]
        assert links and all(u.startswith("file://") and u.endswith(".rrd") for u in links)
        results_table = driver.find_element(By.ID, "toy.v1")
        assert "0.000 [" in results_table.text
        driver.save_screenshot(str(tmp_path / "entry.png"))
        # and the browser requested nothing but files
        urls = [json.loads(m["message"])["message"]["params"]["request"]["url"]
                for m in driver.get_log("performance")
                if json.loads(m["message"])["message"]["method"] == "Network.requestWillBeSent"]
        assert urls and all(u.startswith("file://") for u in urls), [u for u in urls if not u.startswith("file:")]
    finally:
        driver.quit()
    assert (tmp_path / "index.png").stat().st_size > 10_000
