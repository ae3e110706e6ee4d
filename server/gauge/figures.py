"""The gauge study's figures for docs/gauge.md, from the demo's own data:

    python -m server.gauge.figures --out docs/figures

runs ``mvpose demo`` on simulated station 1 with the part held still at its taught reference
(``--max-mm 0 --max-deg 0``, 30 triggers, a temporary data folder), makes the type-1 study of
its records with ``mvpose gauge type1``, and saves the PDF's first page
(``gauge-type1-pdf.png``) and the operator page's study view (``operator-gauge.jpg``, Debian's
Chromium through Playwright, as server.web.screenshots does).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

from server.web.screenshots import STATION1, VIEWPORT, launch, login, serve

DEMO = ["demo", "--triggers", "30", "--max-mm", "0", "--max-deg", "0", "--port", "0"]
TITLE = "mvpose demo, station 1: part held at the taught reference, 30 triggers"


def main(argv: list[str] | None = None) -> int:
    from playwright.sync_api import sync_playwright

    from server.app import create_app
    from server.gauge.report import ReportHeader, first_page_png
    from server.gauge.study import GaugeStudy
    from server.settings import Settings
    from server.store import open_store

    parser = argparse.ArgumentParser(prog="python -m server.gauge.figures",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/figures"))
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    cli = [sys.executable, "-m", "server.cli"]
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "demo"
        subprocess.run([*cli, *DEMO, "--data-dir", str(data)], check=True,
                       stdout=subprocess.DEVNULL)
        subprocess.run([*cli, "gauge", "type1", "--station", str(STATION1), "--data-dir",
                        str(data), "--same-part", "--reference", "0,0,0,0,0,0", "--title",
                        TITLE, "--by", "quality-engineer", "--out", str(Path(tmp) / "report")],
                       check=True)
        store = open_store(f"sqlite:///{data / 'mvpose.db'}", "station1")
        try:
            stored = store.gauge.newest(1)[0]
        finally:
            store.close()
        header = ReportHeader("station1", stored.id, stored.created_at, stored.created_by,
                              stored.hash)
        png = args.out / "gauge-type1-pdf.png"
        png.write_bytes(first_page_png(GaugeStudy.from_json(stored.body), header))
        print(png)
        token = "mvp_gauge-figures-engineer-0123456789"
        settings = Settings(data_dir=data, station=STATION1, bootstrap_token=token,
                            sqlite_synchronous="NORMAL")
        with serve(create_app(settings)) as base, sync_playwright() as pw:
            browser = launch(pw)
            page = browser.new_page(viewport=VIEWPORT)
            login(page, base, token)
            page.goto(f"{base}/gauge/{stored.id}")
            page.wait_for_selector("figure.gauge svg")
            target = args.out / "operator-gauge.jpg"
            page.screenshot(path=str(target), full_page=False, type="jpeg", quality=80)
            print(target)
            browser.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
