"""Packets of one lidar -> sweeps: cut on the publish interval, published in emission order.

A packet belongs to the sweep floor(packet time / publish interval). A sweep is
published once a packet `reorder_slack_ns` past its end has arrived (late
reordered packets still make it), when the lidar goes silent for
`idle_flush_s` on the driver's clock, or on `publish_open` (stop, a time jump).
Points are put back in udp_cnt order; header.stamp = timebase = the first
point's time.
"""

from __future__ import annotations

import itertools
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
        """Packets of one lidar in arrival order: counted, cut where the packet clock jumps, framed."""
        synced = hdr["time_type"] != packets.TIME_TYPE_NO_SYNC
        pkt_ns = np.where(synced, hdr["timestamp"].astype(np.int64), recv_ns)
        with self._lock:
            tracker, seqs, leapt = lidar.points_seq, [], []
            for c, t, w in zip(hdr["udp_cnt"].tolist(), pkt_ns.tolist(), recv_ns.tolist(), strict=True):
                seqs.append(tracker.add(c, t, w))
                leapt.append(tracker.last_leapt)
            keep = np.array([q is not None for q in seqs], bool)
            seq = np.array([q for q in seqs if q is not None], np.int64)
            time_type = int(hdr["time_type"][-1])
            lidar.stats.time_type = time_type
            lidar.stats.unsynced = time_type == packets.TIME_TYPE_NO_SYNC
        if not keep.all():
            hdr, pts, pkt_ns = hdr[keep], pts[keep], pkt_ns[keep]
        if len(pts) == 0:
            return
        lidar.last_packet_wall = self._clock()
        # where the packet clock leapt (SeqTracker: sync gained or lost, a bad sync source, a stray
        # datagram) framing restarts; nothing is dropped
        cuts = np.flatnonzero(np.array(leapt, bool)[keep]).tolist()
        for a, b in itertools.pairwise([0, *[c for c in cuts if c > 0], len(pts)]):
            if a in cuts:
                self.publish_open(lidar)
                lidar.published_key = None
                lidar.newest_ns = None
                with self._lock:
                    lidar.stats.time_jumps += 1
            self._frame(lidar, data_type, hdr[a:b], pts[a:b], seq[a:b], pkt_ns[a:b])

    def _frame(
        self, lidar: LidarState, data_type: int, hdr: Structured, pts: Structured, seq: I64, pkt_ns: I64
    ) -> None:
        """Decode packets of one clock into their sweeps; publish the sweeps now complete."""
        cfg = self.config
        n_pk, dot_num = pts.shape
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
