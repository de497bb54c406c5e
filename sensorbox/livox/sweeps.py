"""Packets of one lidar -> sweeps: cut on the publish interval, published in emission order.

A packet belongs to the sweep floor(packet time / publish interval). A sweep is
published once a packet `reorder_slack_ns` past its end has arrived (late
reordered packets still make it), when the lidar goes silent for
`idle_flush_s` on the driver's clock, or on `publish_open` (stop, a time jump).
Points are put back in udp_cnt order; header.stamp = timebase = the first
point's time.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from calibration.types import I64, Structured
from ingest.bags.livox_msg import POINT_DTYPE
from ingest.bags.rostypes import CUSTOM_MSG_TYPE, POINTCLOUD2_TYPE
from sensorbox import messages
from sensorbox.livox import packets
from sensorbox.livox.config import DriverConfig
from sensorbox.livox.tracking import Chunk, LidarState, to_metres

TIME_JUMP_NS = 1_000_000_000  # a packet this far from the newest one restarts framing (sync gained/lost)
Emit = Callable[[str, str, int, bytes], None]


class SweepAssembler:
    """Open sweeps of every lidar and when to publish them; counters updated under the driver's lock."""

    def __init__(
        self, config: DriverConfig, lock: threading.Lock, clock: Callable[[], float], emit: Emit
    ) -> None:
        self.config = config
        self._lock = lock
        self._clock = clock
        self._emit = emit

    def add(self, lidar: LidarState, data_type: int, hdr: Structured, pts: Structured, recv_ns: I64) -> None:
        cfg = self.config
        with self._lock:
            seqs = [lidar.points_seq.add(c) for c in hdr["udp_cnt"].tolist()]
            keep = np.array([q is not None for q in seqs], bool)
            seq = np.array([q for q in seqs if q is not None], np.int64)
            time_type = int(hdr["time_type"][-1])
            lidar.stats.time_type = time_type
            lidar.stats.unsynced = time_type == packets.TIME_TYPE_NO_SYNC
        if not keep.all():
            hdr, pts, recv_ns = hdr[keep], pts[keep], recv_ns[keep]
        n_pk, dot_num = pts.shape
        if n_pk == 0:
            return
        lidar.last_packet_wall = self._clock()
        synced = hdr["time_type"] != packets.TIME_TYPE_NO_SYNC
        pkt_ns = np.where(synced, hdr["timestamp"].astype(np.int64), recv_ns)
        if lidar.newest_ns is not None and np.abs(pkt_ns - lidar.newest_ns).max() > TIME_JUMP_NS:
            self.publish_open(lidar)  # sync gained or lost: the clocks differ, start framing afresh
            lidar.published_key = None
            lidar.newest_ns = None
            with self._lock:
                lidar.stats.time_jumps += 1
        stamps = packets.point_times_ns(pkt_ns, hdr["time_interval"], hdr["dot_num"], dot_num)
        xyz = to_metres(data_type, packets.native_xyz(data_type, pts), lidar.endpoint.extrinsic).astype(
            np.float32
        )
        line = np.broadcast_to((np.arange(dot_num) % 4).astype(np.uint8), (n_pk, dot_num))
        keys = pkt_ns // cfg.publish_interval_ns
        late = 0
        for key in np.unique(keys).tolist():
            sel = keys == key
            if lidar.published_key is not None and key <= lidar.published_key:
                late += int(sel.sum())
                continue
            lidar.frames.setdefault(key, []).append(
                Chunk(
                    seq[sel], stamps[sel].ravel(), xyz[sel].reshape(-1, 3), pts["reflectivity"][sel].ravel(),
                    pts["tag"][sel].ravel(), line[sel].ravel(),
                )
            )  # fmt: skip
        with self._lock:
            lidar.stats.late += late
            lidar.stats.packets += n_pk - late
        newest = int(pkt_ns.max())
        lidar.newest_ns = newest if lidar.newest_ns is None else max(lidar.newest_ns, newest)
        ready = [
            k
            for k in lidar.frames
            if (k + 1) * cfg.publish_interval_ns + cfg.reorder_slack_ns <= lidar.newest_ns
        ]
        for key in sorted(ready):
            self._publish(lidar, key)

    def flush_idle(self, lidars: Iterable[LidarState]) -> None:
        now = self._clock()
        for lidar in lidars:
            if lidar.frames and now - lidar.last_packet_wall > self.config.idle_flush_s:
                self.publish_open(lidar)

    def publish_open(self, lidar: LidarState) -> None:
        for key in sorted(lidar.frames):
            self._publish(lidar, key)

    def _publish(self, lidar: LidarState, key: int) -> None:
        chunks = lidar.frames.pop(key)
        lidar.published_key = key if lidar.published_key is None else max(lidar.published_key, key)
        # emission order (udp_cnt), which undoes reordering; with host-clock stamps packets received
        # in a burst overlap in time, so sorting by stamp would interleave their points
        seq = np.concatenate([c.seq for c in chunks])
        order = None
        if (np.diff(seq) < 0).any():
            per_point = [np.repeat(c.seq, len(c.stamps_ns) // len(c.seq)) for c in chunks]
            order = np.argsort(np.concatenate(per_point), kind="stable")
        stamps = np.concatenate([c.stamps_ns for c in chunks])
        points = np.empty(len(stamps), POINT_DTYPE)

        def take(a: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
            return a if order is None else a[order]

        stamps = take(stamps)
        timebase = int(stamps.min())  # the first point's time; min() guards host-clock jitter
        xyz = take(np.concatenate([c.xyz_m for c in chunks]))
        points["offset_time"] = (stamps - timebase).astype(np.uint32)
        points["x"], points["y"], points["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        points["reflectivity"] = take(np.concatenate([c.reflectivity for c in chunks]))
        points["tag"] = take(np.concatenate([c.tag for c in chunks]))
        points["line"] = take(np.concatenate([c.line for c in chunks]))
        ros = self.config.ros_version
        if self.config.msg_format == "custom":
            raw = messages.custom_msg(timebase, points, ros, lidar_id=lidar.lidar_id)
            msgtype = CUSTOM_MSG_TYPE
        else:
            raw = messages.pointcloud2_msg(timebase, points, ros)
            msgtype = POINTCLOUD2_TYPE
        self._emit(lidar.topic, msgtype, timebase, raw)
        with self._lock:
            lidar.stats.sweeps += 1
            lidar.stats.points += len(points)
