"""ROS 2 topics as rmw_zenoh puts them on Zenoh: key expressions and the attachment, built and parsed here.

The format followed is that of ros2/rmw_zenoh's ``rmw_zenoh_cpp`` 0.2 (ROS 2 Jazzy, zenoh 1.x;
the same in Kilted and Rolling), read from its sources (``liveliness_utils.cpp``,
``attachment_helpers.cpp``); no ROS runtime could be installed here, so it was tested against
:mod:`protocol.ros_camera`'s own publisher, written from the same reading:

- a message goes to ``<domain_id>/<topic without its leading and trailing '/'>/<DDS type
  name>/<type hash>``, e.g. ``0/camera/image_raw/sensor_msgs::msg::dds_::Image_/RIHS01_d31d...``
  (Humble's rmw_zenoh says ``TypeHashNotSupported`` where the hash goes);
- its payload is the message's CDR, encapsulation header included (what a rosbag2 stores);
- its attachment is zenoh's ext serialisation of (int64 sequence number, int64 source timestamp
  in ns, the publisher's 16-byte gid as a sequence): 8 + 8 + 1 (LEB128 length 16) + 16 bytes,
  little endian. The gid identifies one publisher of one process; a restarted publisher has a new
  one and counts its sequence from 1 again.

Pure: no Zenoh, no torch (:mod:`protocol.ros_camera` is the session).
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

__all__ = ["Attachment", "AttachmentError", "dds_type_name", "ros_type_name", "topic_key", "topic_key_pattern",
           "parse_topic_key", "HASH_NOT_SUPPORTED", "GID_SIZE"]

GID_SIZE = 16  # RMW_GID_STORAGE_SIZE since Iron
HASH_NOT_SUPPORTED = "TypeHashNotSupported"  # Humble's rmw_zenoh: no type hashes
_ATTACHMENT = struct.Struct("<qqB16s")
_DDS = re.compile(r"^([A-Za-z][\w]*)::(msg|srv|action)::dds_::([A-Za-z]\w*)_$")
_TOPIC = re.compile(r"^(/[A-Za-z_~{][\w{}~]*)+$")


class AttachmentError(ValueError):
    """An attachment that is not rmw_zenoh's (its length or its gid's length is wrong)."""


@dataclass(frozen=True)
class Attachment:
    sequence_number: int  # per publisher, from 1
    source_timestamp_ns: int  # the publisher's clock when it published
    gid: bytes  # [16] the publisher

    def encode(self) -> bytes:
        if len(self.gid) != GID_SIZE:
            raise AttachmentError(f"a gid has {GID_SIZE} bytes, got {len(self.gid)}")
        return _ATTACHMENT.pack(self.sequence_number, self.source_timestamp_ns, GID_SIZE, self.gid)

    @classmethod
    def decode(cls, raw: bytes | None) -> "Attachment":
        if raw is None:
            raise AttachmentError("no attachment (rmw_zenoh sends a sequence number, a timestamp and a gid)")
        if len(raw) != _ATTACHMENT.size:
            raise AttachmentError(f"an rmw_zenoh attachment has {_ATTACHMENT.size} bytes, got {len(raw)}")
        seq, stamp, n, gid = _ATTACHMENT.unpack(raw)
        if n != GID_SIZE:
            raise AttachmentError(f"the attachment's gid has {n} bytes, expected {GID_SIZE}")
        return cls(seq, stamp, gid)


def dds_type_name(ros_type: str) -> str:
    """``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_`` (how rmw_zenoh names types)."""
    parts = ros_type.split("/")
    if len(parts) != 3 or parts[1] not in ("msg", "srv", "action") or not all(parts):
        raise ValueError(f"not a ROS 2 type name (package/msg/Name): {ros_type!r}")
    return f"{parts[0]}::{parts[1]}::dds_::{parts[2]}_"


def ros_type_name(dds: str) -> str:
    """The inverse of :func:`dds_type_name`."""
    m = _DDS.match(dds)
    if m is None:
        raise ValueError(f"not an rmw_zenoh type name (pkg::msg::dds_::Name_): {dds!r}")
    return f"{m.group(1)}/{m.group(2)}/{m.group(3)}"


def _check_topic(topic: str) -> str:
    if not _TOPIC.match(topic.rstrip("/")):
        raise ValueError(f"not an absolute ROS 2 topic name: {topic!r}")
    return topic.strip("/")


def topic_key(domain_id: int, topic: str, ros_type: str, type_hash: str) -> str:
    """The key expression rmw_zenoh publishes ``topic`` on."""
    if not 0 <= int(domain_id) <= 232:
        raise ValueError(f"a ROS domain id is in 0..232, got {domain_id}")
    if not type_hash or "/" in type_hash or "*" in type_hash:
        raise ValueError(f"not a type hash: {type_hash!r}")
    return f"{int(domain_id)}/{_check_topic(topic)}/{dds_type_name(ros_type)}/{type_hash}"


def topic_key_pattern(domain_id: int, topic: str, ros_type: str) -> str:
    """What a subscriber declares: the topic with any type hash (it checks the hash itself)."""
    return f"{int(domain_id)}/{_check_topic(topic)}/{dds_type_name(ros_type)}/*"


def parse_topic_key(key: str) -> tuple[int, str, str, str]:
    """``<domain>/<topic...>/<type>/<hash>`` -> (domain, ``/topic``, ROS type, hash); ValueError otherwise."""
    parts = key.split("/")
    if len(parts) < 4 or not parts[0].isdigit():
        raise ValueError(f"not an rmw_zenoh topic key: {key!r}")
    return int(parts[0]), "/" + "/".join(parts[1:-2]), ros_type_name(parts[-2]), parts[-1]
