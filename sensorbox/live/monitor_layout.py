"""The Foxglove layout shipped for the live monitor (`sensorbox/share/foxglove/monitor_layout.json`).

Built with foxglove-sdk's layout types from the monitor's channels of a rig
(the reference rig for the shipped file, which a test keeps in step with this
code): the upper, lower and coverage images in the top row; both LiDARs in a
3D view in cam0, plots of the coverage fraction, the LiDARs' written rates and
the gyros (in cam0), and the raw status in the bottom row.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from calibration.rig import Rig
from sensorbox.live.monitor_channels import STATUS_TOPIC, streams_of

LAYOUT_FILE = Path(__file__).resolve().parents[1] / "share" / "foxglove" / "monitor_layout.json"


def monitor_layout(rig: Rig) -> dict[str, Any]:
    """The layout as the JSON object Foxglove imports (Layouts > Import from file)."""
    import foxglove.layouts as fl

    streams = {s.channel: s for s in streams_of(rig).values()}
    lidars = [s for s in streams.values() if s.kind == "lidar"]
    imus = [s for s in streams.values() if s.kind == "imu"]

    def image(topic: str, title: str) -> Any:
        return fl.ImagePanel(
            title=title, config=fl.ImageConfig(image_mode=fl.ImageModeConfig(image_topic=topic))
        )

    clouds: dict[str, Any] = {
        s.channel: fl.BaseRendererPointCloudTopicSettings(
            visible=True, point_size=2.0, color_mode="colormap", color_field="intensity", color_map="turbo"
        )
        for s in lidars
    }
    three_d = fl.ThreeDeePanel(
        title="LiDARs in cam0", config=fl.ThreeDeeConfig(topics=clouds, fixed_frame="cam0", follow_tf="cam0")
    )
    series = [fl.PlotSeries(value=f"{STATUS_TOPIC}.coverage_fraction", label="coverage (fraction of pixels)")]
    rates = [
        fl.PlotSeries(value=f'{STATUS_TOPIC}.topics[:]{{topic=="{topic}"}}.rate_hz', label=f"{s.name} Hz")
        for topic, s in streams_of(rig).items()
        if s.kind == "lidar"
    ]
    gyro = [
        fl.PlotSeries(value=f"{imu.channel}.gyro_rad_s.{axis}", label=f"{imu.name} gyro {axis} rad/s")
        for imu in imus
        for axis in "xyz"
    ]
    row = [
        fl.SplitItem(content=three_d, proportion=1.4),
        fl.SplitItem(content=fl.PlotPanel(title="Coverage", config=fl.PlotConfig(paths=series))),
        fl.SplitItem(
            content=fl.PlotPanel(title="LiDAR rates and gyro", config=fl.PlotConfig(paths=rates + gyro))
        ),
        fl.SplitItem(
            content=fl.RawMessagesPanel(title="Status", config=fl.RawMessagesConfig(topic_path=STATUS_TOPIC))
        ),
    ]
    top = [
        fl.SplitItem(content=image("/monitor/upper/image", "Upper camera")),
        fl.SplitItem(content=image("/monitor/lower/image", "Lower camera")),
        fl.SplitItem(content=image("/monitor/coverage", "Coverage preview (last second of both LiDARs)")),
    ]
    layout = fl.Layout(
        content=fl.SplitContainer(
            direction="column",
            items=[
                fl.SplitItem(content=fl.SplitContainer(direction="row", items=top)),
                fl.SplitItem(content=fl.SplitContainer(direction="row", items=row)),
            ],
        )
    )
    out: dict[str, Any] = json.loads(layout.to_json())
    return out


def layout_text(rig: Rig) -> str:
    """The layout file's text: indented JSON, one trailing newline."""
    return json.dumps(monitor_layout(rig), indent=2) + "\n"
