"""The node's health: the ``~/status`` JSON counters and the ``/diagnostics`` entry."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from mfp_mapper.config.schema import NodeConfig
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.mapping.live import LiveCounters, finite_or_none
from mfp_mapper.ros.map_outputs import OCTOMAP_TOPICS, TOPICS, PublishCounters


@dataclass
class StatusWindow:
    """The counters at the previous report, for rates and "since last time"."""

    time: float
    rays_used: int = 0
    cpu: float = 0.0
    clouds_in: int = 0
    clouds_integrated: int = 0
    clouds_dropped: int = 0
    clouds_lost_transport: int = 0
    clouds_localized: int = 0
    queue_full: int = 0


def status_report(
    c: LiveCounters,
    queued: int,
    map_figures: tuple[int, int, int],
    publish: PublishCounters,
    window: StatusWindow,
    extra: dict[str, Any],
) -> dict[str, Any]:
    """The ``~/status`` dictionary (counters, rates since ``window``, map figures)."""
    now = time.monotonic()
    voxels, memory, version = map_figures
    span = max(now - window.time, 1e-9)
    n_int = max(c.clouds_integrated, 1)
    return {
        **extra,
        "clouds_in": c.clouds_in,
        "clouds_lost_transport": c.clouds_lost_transport,
        "clouds_integrated": c.clouds_integrated,
        "clouds_localized": c.clouds_localized,
        "clouds_dropped": dict(c.clouds_dropped),
        "points_in": c.points_in,
        "points_dropped": dict(c.points_dropped),
        "queued": queued,
        "behind": c.clouds_dropped["queue_full"] > window.queue_full,
        "rays_in": c.rays_in,
        "rays_used": c.rays_used,
        "rays_truncated": c.rays_truncated,
        "rays_cut_by_budget": c.rays_cut_by_budget,
        "rays_no_return": c.rays_no_return,
        "rays_per_s": round((c.rays_used - window.rays_used) / span, 1),
        "integration_cpu_share": round((c.integration_cpu - window.cpu) / span, 4),
        "integration_cpu_s": round(c.integration_cpu, 4),
        "integration_wall_s": round(c.integration_wall, 4),
        "latency_last_s": finite_or_none(c.latency_last),
        "latency_mean_s": c.latency_sum / n_int if c.clouds_integrated else None,
        "latency_max_s": c.latency_max if c.clouds_integrated else None,
        "received_latency_mean_s": c.received_latency_sum / n_int if c.clouds_integrated else None,
        "received_latency_max_s": c.received_latency_max if c.clouds_integrated else None,
        "stage_s": {k: round(v, 4) for k, v in c.stage_seconds.items()},
        "odom_in": c.odom_in,
        "odom_rejected": dict(c.odom_rejected),
        "tf_in": c.tf_in,
        "tf_rejected": dict(c.tf_rejected),
        "voxels": voxels,
        "memory_bytes": memory,
        "map_version": version,
        "publish_count": publish.count,
        "publish_last_s": round(publish.last_seconds, 5),
        "publish_total_s": round(publish.seconds, 4),
        "publish_locked_total_s": round(publish.locked_seconds, 4),
        "publish_locked_max_s": round(publish.locked_max_seconds, 4),
        "publish_slices": publish.slices,
        "map_wait_max_s": round(c.map_wait_max, 4),
        "published_voxels": publish.voxels,
        "published_blocks_read": publish.blocks_read,
    }


def next_window(c: LiveCounters) -> StatusWindow:
    return StatusWindow(
        time.monotonic(),
        c.rays_used,
        c.integration_cpu,
        c.clouds_in,
        c.clouds_integrated,
        sum(c.clouds_dropped.values()),
        c.clouds_lost_transport,
        c.clouds_localized,
        c.clouds_dropped["queue_full"],
    )


def health(status: dict[str, Any], window: StatusWindow) -> tuple[bytes, str]:
    """Level (DiagnosticStatus OK, WARN or ERROR) and message for the last window."""
    arrived = status["clouds_in"] - window.clouds_in
    integrated = status["clouds_integrated"] - window.clouds_integrated
    localized = status.get("clouds_localized", 0) - window.clouds_localized
    dropped = sum(status["clouds_dropped"].values()) - window.clouds_dropped
    lost = status["clouds_lost_transport"] - window.clouds_lost_transport
    if arrived == 0:
        return DiagnosticStatus.WARN, "no cloud received"
    if localized and not integrated:  # localization against a frozen map
        if dropped or lost:
            return (
                DiagnosticStatus.WARN,
                f"{localized} of {arrived} clouds localized, {dropped} dropped, "
                f"{lost} lost in transport",
            )
        return DiagnosticStatus.OK, f"{localized} clouds localized (map frozen)"
    if integrated == 0:
        reasons = ", ".join(f"{k} {v}" for k, v in sorted(status["clouds_dropped"].items()))
        return (
            DiagnosticStatus.ERROR,
            f"{arrived} clouds received, none integrated (drops so far: {reasons or 'none'})",
        )
    skipped = status["clouds_dropped"].get("queue_full", 0) - window.queue_full
    if skipped > 0:
        return (
            DiagnosticStatus.WARN,
            f"integration is behind the input: {integrated} of {arrived} clouds integrated, "
            f"{skipped} skipped (queue_full: the oldest queued dropped), {dropped - skipped} "
            f"dropped otherwise, {lost} lost in transport",
        )
    if dropped or lost:
        return (
            DiagnosticStatus.WARN,
            f"{integrated} of {arrived} clouds integrated, {dropped} dropped, "
            f"{lost} lost in transport",
        )
    return DiagnosticStatus.OK, f"{integrated} clouds integrated"


def diagnostics(
    status: dict[str, Any], window: StatusWindow, name: str, hardware_id: str, stamp: Any
) -> DiagnosticArray:
    """A ``/diagnostics`` message with one status: the node's health and its counters."""
    level, message = health(status, window)
    entry = DiagnosticStatus(
        level=level,
        name=name,
        message=message,
        hardware_id=hardware_id,
        values=[
            KeyValue(key=key, value=str(value))
            for key, value in status.items()
            if not isinstance(value, dict)
        ]
        + [
            KeyValue(key=f"{key}.{sub}", value=str(v))
            for key, value in status.items()
            if isinstance(value, dict)
            for sub, v in sorted(value.items())
        ],
    )
    out = DiagnosticArray()
    out.header.stamp = stamp
    out.status = [entry]
    return out


def localization_diagnostic(
    report: dict[str, Any], name: str, hardware_id: str
) -> DiagnosticStatus:
    """The localization's ``/diagnostics`` entry: OK when localized, WARN while waiting for
    a map or a first accepted correction, ERROR when lost."""
    state = report["state"]
    level = {"localized": DiagnosticStatus.OK, "lost": DiagnosticStatus.ERROR}.get(
        state, DiagnosticStatus.WARN
    )
    last = report.get("last") or {}
    message = state
    if last:
        verdict = "accepted" if last["accepted"] else f"refused: {last['reason']}"
        message += (
            f"; last correction {last['shift_m']:.3f} m, {last['angle_deg']:.2f} deg ({verdict})"
        )
    values: list[KeyValue] = []
    for key, value in report.items():
        if isinstance(value, dict):
            values += [KeyValue(key=f"{key}.{k}", value=str(v)) for k, v in sorted(value.items())]
        else:
            values.append(KeyValue(key=key, value=str(value)))
    return DiagnosticStatus(
        level=level, name=name, message=message, hardware_id=hardware_id, values=values
    )


def startup_text(cfg: NodeConfig, topic: Callable[[str], str], mapper: Mapper, frame: str) -> str:
    """The start-up log line: what a robot integrator needs to check (topics, the map frame
    and the rule that decides it, pose and extrinsic sources, map file, outputs); ``topic``
    resolves a topic name; ``frame`` is the map frame when already decided."""
    names = OCTOMAP_TOPICS if cfg.outputs.octomap_topics else TOPICS
    if cfg.placement.lidar_override() is not None:
        extrinsic = (
            f"lidar.* parameters (translation {list(cfg.placement.lidar_translation)}, rpy "
            f"{list(cfg.placement.lidar_rpy)}) unless the cloud frame is the odometry child"
        )
    else:
        body = cfg.placement.base_frame_id or "<odometry child>"
        extrinsic = (
            f"/tf_static {body} -> cloud frame (identity when the cloud frame is the "
            "odometry child; a cloud it cannot place is dropped)"
        )
    if cfg.map.frame_id:
        map_frame = f"{frame!r} (frame_id; clouds wait for TF to reach it)"
    elif frame:
        map_frame = f"{frame!r} (the loaded map's)"
    else:
        map_frame = (
            "decided at the first cloud placed (the odometry frame, else the root of the "
            "cloud's TF tree; logged) and then fixed for the run"
        )
    poses = (
        f"{topic('odom')} (nav_msgs/Odometry) when it publishes, linked to the map frame "
        f"through TF; else TF map frame <- cloud frame; /tf and /tf_static "
        f"(tf2_msgs/TFMessage, cache {cfg.placement.tf_buffer} s)"
    )
    if cfg.localization.enabled:
        odom = cfg.localization.odom_frame
        map_frame = (
            f"{frame!r} (frame_id, else the loaded map's unless it is the odometry frame, "
            "else 'map')"
        )
        poses = (
            f"{topic('odom')} or TF in {odom!r}, localized against the map (map -> {odom} "
            f"on /tf: {cfg.localization.tf_publish}; freeze_map "
            f"{cfg.localization.freeze_map}; {topic('initialpose')} resets it)"
        )
    path = cfg.node.map_path or "<none>"
    loaded = f", {mapper.num_voxels} voxels loaded" if mapper.num_voxels else ""
    max_range, decay = cfg.sensor_model.core("max_range"), cfg.map.core("decay_time")
    out = cfg.outputs
    return (
        f"mfp_mapper ready: clouds from {topic('cloud_in')}, poses from {poses}; map frame "
        f"{map_frame}; extrinsic: {extrinsic}; resolution "
        f"{mapper.resolution} m, max_range {max_range} m, decay_time "
        f"{decay} s, deskew {cfg.placement.deskew}, threads {mapper.threads}"
        f"{' (automatic)' if cfg.map.threads <= 0 else ''}; map_path {path}{loaded}, "
        "save_on_shutdown "
        f"{cfg.node.save_on_shutdown}; outputs {topic(names['degree_of_occupancy'])}, "
        f"{topic(names['std'])}, {topic(names['projected_map'])} (trinary "
        f"{out.projected_map_trinary}) at {out.publish_rate} Hz, latched {out.latch}"
    )


def localization_line(status: dict[str, Any]) -> str:
    """The status line's localization part ("" when not localizing)."""
    loc = status.get("localization")
    if not loc:
        return ""
    refused = ", ".join(f"{k} {v}" for k, v in sorted(loc["refused"].items())) or "none"
    m = loc["map_to_odom"]
    return (
        f"; localization {loc['state']}: {loc['accepted']} of {loc['aligned']} alignments "
        f"accepted (refused: {refused}), map -> odom x {m['x']:.3f} y {m['y']:.3f} yaw "
        f"{m['yaw_deg']:.2f} deg"
    )
