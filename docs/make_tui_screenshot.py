"""Regenerates docs/dashboard_tui.png: `dashboard tui` fed by a live `actuatord --sim` (30 kg
payload, the paper's sinusoid) for six seconds. Needs cairosvg (pip install cairosvg).

    python docs/make_tui_screenshot.py
"""

import asyncio
import json
import subprocess
import sys

import cairosvg
import zenoh

from dashboard.tui import ElbowDashboard, Feed
from protocol import telemetry

PORT = 7461


def main() -> None:
    actuatord = subprocess.Popen(
        [sys.executable, "-m", "commands.actuatord", "--sim", "--duration", "30", "--payload-mass",
         "30", "--payload-position", "0,0.05", "--listen", f"tcp/127.0.0.1:{PORT}",
         "--no-multicast-scouting"], stdout=subprocess.PIPE, text=True)
    actuatord.stdout.readline()
    config = zenoh.Config()
    config.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{PORT}"]))
    config.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(config)
    feed = Feed(session, telemetry.DEFAULT_PREFIX)

    async def scenario() -> str:
        app = ElbowDashboard(feed)
        async with app.run_test(size=(110, 42)) as pilot:
            await pilot.pause(6.0)
            return app.export_screenshot()

    svg = asyncio.run(scenario())
    feed.close()
    session.close()
    actuatord.terminate()
    actuatord.wait(30)
    cairosvg.svg2png(bytestring=svg.encode(), write_to="docs/dashboard_tui.png",
                     output_width=1400)
    print("wrote docs/dashboard_tui.png")


if __name__ == "__main__":
    main()
