"""Reading Foxglove messages as the Foxglove app does: protobuf decoded with the schema a channel
advertises (a FileDescriptorSet), and the geometry of a decoded pose."""
import numpy as np
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory


def decoder(schema_name: str, descriptor_set: bytes):
    """A function from a message's protobuf bytes to the message, for the schema ``schema_name``
    whose FileDescriptorSet is ``descriptor_set`` (what a Foxglove channel advertises)."""
    pool = descriptor_pool.DescriptorPool()
    for f in descriptor_pb2.FileDescriptorSet.FromString(descriptor_set).file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name)).FromString


def rotate(q, v) -> np.ndarray:
    """The vector v rotated by the unit quaternion q (a decoded foxglove.Quaternion)."""
    u, w = np.array([q.x, q.y, q.z]), q.w
    v = np.asarray(v, dtype=float)
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def cylinder_ends(c) -> tuple:
    """The centres (bottom, top) [m] of a decoded foxglove.CylinderPrimitive's faces."""
    center = np.array([c.pose.position.x, c.pose.position.y, c.pose.position.z])
    half = rotate(c.pose.orientation, [0.0, 0.0, 0.5 * c.size.z])
    return center - half, center + half
