"""Message schemas of a cbh recording: Foxglove protobuf types plus cbh's own typed messages.

cbh's own messages (``cbh.PairLayers``, ``cbh.Histogram``, ``cbh.Matches``, ``cbh.ServiceStatus``)
are protobuf types built at run time from a ``FileDescriptorProto`` (no generated code, no
``protoc``). Each MCAP schema record carries the full ``FileDescriptorSet`` (encoding
``protobuf``), so generic tools (Foxglove, ``mcap_protobuf``'s decoder, Rerun's schema
reflection) decode them without cbh.

All doubles are stored as ``double``: the layer heights read back bit for bit.
"""
from __future__ import annotations

from functools import lru_cache

__all__ = ["cbh_types", "foxglove_types", "SCHEMA_PACKAGE"]

SCHEMA_PACKAGE = "cbh"

# (message name, [(field name, number, type, label, type_name)])
_D, _F, _U32, _U64, _S, _M = "double", "float", "uint32", "uint64", "string", "message"
_OPT = "optional"  # label: proto3 optional (explicit presence)
_MESSAGES: list[tuple[str, list[tuple]]] = [
    ("Layer", [
        ("height_m", 1, _D, False, None),  # cloud-base height above the ENU origin [m]
        ("median_height_m", 2, _D, False, None),
        ("spread_m", 3, _D, False, None),
        ("cover", 4, _D, False, None),  # 0..1
        ("points", 5, _U32, False, None),
        ("confidence", 6, _D, False, None),  # 0..1
        ("altitude_m", 7, _D, False, None),  # height_m + station altitude [m above sea level]
        # proto3 ``optional`` (field presence): absent in recordings made before motion existed,
        # which read back as NaN (unknown), never as 0 m/s
        ("motion_east_ms", 8, _D, _OPT, None),  # layer motion over the ground, east [m/s]
        ("motion_north_ms", 9, _D, _OPT, None),  # layer motion over the ground, north [m/s]
        ("motion_spread_ms", 10, _D, _OPT, None),  # robust spread of the track velocities [m/s]
        ("motion_tracks", 11, _U32, False, None),  # feature tracks behind the motion (0 = none)
        # the layer's band (Layer.height_lo_m / height_hi_m) [m]; absent = unknown (NaN)
        ("height_lo_m", 12, _D, _OPT, None),
        ("height_hi_m", 13, _D, _OPT, None),
    ]),
    ("Diagnostic", [("name", 1, _S, False, None), ("value", 2, _D, False, None)]),  # PairResult.diagnostics
    ("CloudFraction", [("camera", 1, _S, False, None), ("fraction", 2, _D, False, None)]),
    ("Timing", [("stage", 1, _S, False, None), ("ms", 2, _D, False, None)]),
    ("PairLayers", [
        ("timestamp", 1, _M, False, ".google.protobuf.Timestamp"),
        ("camera1", 2, _S, False, None),
        ("camera2", 3, _S, False, None),
        ("layers", 4, _M, True, ".cbh.Layer"),
        ("cloud_fraction", 5, _M, True, ".cbh.CloudFraction"),
        ("flags", 6, _S, True, None),
        ("timing", 7, _M, True, ".cbh.Timing"),
        ("point_count", 8, _U32, False, None),
        ("pair_index", 9, _U64, False, None),
        ("diagnostics", 10, _M, True, ".cbh.Diagnostic"),  # named scalar quality measures (units in names)
        ("flag_bits", 11, _U64, False, None),  # cbh.flags.flag_bits(flags): fixed bits of cbh.flags.Flag
        # /pair/height_map holds camera 1's map decimated by this factor: it was a nearest-neighbour
        # upsample (each f × f block one height), recorded losslessly at 1/f² the size; 0 or 1 = full size
        ("height_map_scale", 12, _U32, False, None),
    ]),
    ("Histogram", [
        ("timestamp", 1, _M, False, ".google.protobuf.Timestamp"),
        ("edges_m", 2, _D, True, None),  # B + 1 bin edges [m]
        ("counts", 3, _D, True, None),  # B (weighted) counts
    ]),
    ("MatchSet", [
        ("method", 1, _S, False, None),
        ("x1", 2, _D, True, None), ("y1", 3, _D, True, None),  # camera 1 pixels
        ("x2", 4, _D, True, None), ("y2", 5, _D, True, None),  # camera 2 pixels
    ]),
    ("Matches", [
        ("timestamp", 1, _M, False, ".google.protobuf.Timestamp"),
        ("camera1", 2, _S, False, None),
        ("camera2", 3, _S, False, None),
        ("sets", 4, _M, True, ".cbh.MatchSet"),
    ]),
    ("Counter", [("name", 1, _S, False, None), ("value", 2, _D, False, None)]),
    ("SourceState", [("name", 1, _S, False, None), ("state", 2, _S, False, None)]),
    ("ServiceStatus", [
        ("timestamp", 1, _M, False, ".google.protobuf.Timestamp"),
        ("counters", 2, _M, True, ".cbh.Counter"),
        ("sources", 3, _M, True, ".cbh.SourceState"),
        ("json", 4, _S, False, None),  # the full stats object as JSON
    ]),
]


@lru_cache(maxsize=1)
def cbh_types() -> dict:
    """Message classes of cbh's own schemas, by short name (``"PairLayers"`` …)."""
    from google.protobuf import descriptor_pb2, descriptor_pool, timestamp_pb2
    from google.protobuf.message_factory import GetMessageClass

    fdp = descriptor_pb2.FileDescriptorProto(
        name="cbh/messages.proto", package=SCHEMA_PACKAGE, syntax="proto3",
        dependency=["google/protobuf/timestamp.proto"],
    )
    types = {
        _D: descriptor_pb2.FieldDescriptorProto.TYPE_DOUBLE,
        _F: descriptor_pb2.FieldDescriptorProto.TYPE_FLOAT,
        _U32: descriptor_pb2.FieldDescriptorProto.TYPE_UINT32,
        _U64: descriptor_pb2.FieldDescriptorProto.TYPE_UINT64,
        _S: descriptor_pb2.FieldDescriptorProto.TYPE_STRING,
        _M: descriptor_pb2.FieldDescriptorProto.TYPE_MESSAGE,
    }
    for name, fields in _MESSAGES:
        m = fdp.message_type.add(name=name)
        for fname, num, ftype, repeated, type_name in fields:
            f = m.field.add(name=fname, number=num, type=types[ftype])
            f.label = (descriptor_pb2.FieldDescriptorProto.LABEL_REPEATED if repeated is True
                       else descriptor_pb2.FieldDescriptorProto.LABEL_OPTIONAL)
            if repeated == _OPT:  # proto3 optional = a synthetic one-field oneof
                f.proto3_optional = True
                f.oneof_index = len(m.oneof_decl)
                m.oneof_decl.add(name=f"_{fname}")
            if type_name:
                f.type_name = type_name
    pool = descriptor_pool.DescriptorPool()
    ts = descriptor_pb2.FileDescriptorProto()
    timestamp_pb2.DESCRIPTOR.CopyToProto(ts)
    pool.Add(ts)
    pool.Add(fdp)
    return {name: GetMessageClass(pool.FindMessageTypeByName(f"{SCHEMA_PACKAGE}.{name}")) for name, _ in _MESSAGES}


def foxglove_types() -> dict:
    """The Foxglove protobuf classes a recording uses, by short name."""
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    return {"CompressedImage": CompressedImage, "RawImage": RawImage, "PointCloud": PointCloud,
            "PackedElementField": PackedElementField}
