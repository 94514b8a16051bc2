"""Where ``up``'s views come from when they arrive while it trains: a bag replayed, or the live camera.

The one place that joins the stream (``agent.data.stream``, no Zenoh) to the robot's own ROS 2
topics over Zenoh (``protocol.ros_camera``, no torch), as ``up`` joins the daemon to its transport.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from agent.data.ros.bag import CAMERA_INFO, COMPRESSED, IMAGE, TF
from agent.data.ros.intake import FrameIntake, bag_image_topic, replay_bag
from agent.data.stream import ViewStream
from agent.data.views import Views
from cli.errors import UserError

DEFAULT_IMAGE_TOPIC = "/camera/image_raw"


class StreamSource:
    """A started :class:`ViewStream` and what feeds it; :meth:`close` stops both."""

    def __init__(self, stream: ViewStream, describe: str, subscriber=None) -> None:
        self.stream, self.describe, self.subscriber = stream, describe, subscriber

    def close(self) -> None:
        if self.subscriber is not None:
            self.subscriber.close()
        self.stream.close()


def _info_topic(image_topic: str) -> str:
    """image_transport's convention: ``/ns/camera/image_raw`` -> ``/ns/camera/camera_info``."""
    return image_topic.rsplit("/", 1)[0] + "/camera_info" if image_topic.count("/") > 1 else "/camera_info"


def open_stream(cfg, data: Path, run_keyframes: Path, replay: float | None, live: list[str],
                log: Callable[[str], None]) -> StreamSource:
    """``cfg``: the swarm file's config (``data.ros``, ``data.stream``, ``training``)."""
    ros, sc, training = cfg.data.ros, cfg.data.stream, cfg.training
    capacity = sc.capacity or ros.keyframes.max_keyframes
    if replay is not None:
        if replay < 0:
            raise UserError(f"--replay {replay}: the pace must be >= 0 (1.0: as recorded; 0: as fast as it reads)")
        image_topic, info_topic = bag_image_topic(data, ros)
    else:
        image_topic = ros.image_topic or DEFAULT_IMAGE_TOPIC
        info_topic = ros.camera_info_topic or _info_topic(image_topic)
    intake = FrameIntake(ros, image_topic, info_topic, sc.tf_wait_s)
    stream = ViewStream(sc, intake, run_keyframes, training.image_width, training.own_holdout_every, capacity)
    if replay is not None:
        stream.run_in_background(lambda stop: replay_bag(data, intake, replay, stop))
        return StreamSource(stream, f"replaying {data} at {replay:g}x its recorded pace ({image_topic})")
    from protocol.ros_camera import RosTopicSubscriber

    topics = [(image_topic, IMAGE), (image_topic, COMPRESSED), (info_topic, CAMERA_INFO), ("/tf", TF), ("/tf_static", TF)]
    refused: dict[str, int] = {}

    def on_refused(reason: str, detail: str) -> None:
        refused[reason] = refused.get(reason, 0) + 1
        if refused[reason] <= 3:
            log(f"refused a ROS message ({reason}, #{refused[reason]}): {detail[:200]}")

    sub = RosTopicSubscriber(live, topics, lambda m: intake.feed(m.topic, m.ros_type, m.message, m.received_ns),
                             sc.domain_id, on_refused, connect_timeout_s=min(sc.start_timeout_s, 30.0))
    try:
        sub.open()
    except ConnectionError as e:
        stream.close()
        raise UserError(str(e)) from None
    return StreamSource(stream, f"live camera {image_topic} over Zenoh from {', '.join(live)} (domain {sc.domain_id})",
                        sub)


def start_stream(cfg, data: Path, run_keyframes: Path, replay: float | None, live: list[str],
                 log: Callable[[str], None]) -> tuple[StreamSource, Views, Views | None]:
    """Open the stream and wait for its first keyframes: (source, training views, summary views or None)."""
    source = open_stream(cfg, data, run_keyframes, replay, live, log)
    try:
        source.stream.wait_for_start(lambda t: log(f"{source.describe}: {t}"))
        views, summary = source.stream.initial_views(), None
        if cfg.daemon.initial_pose == "coarse" and cfg.daemon.summary_width != cfg.training.image_width:
            summary = source.stream.initial_views(cfg.daemon.summary_width)  # sharper features for the summary
        return source, views, summary if summary is not None and summary.width != views.width else None
    except BaseException:
        source.close()
        raise
