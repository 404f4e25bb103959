"""MCAP recording of cbh sessions: recorder, reader and recovery.

One file per session (optionally rotated by size or time). Every message's log time is the
capture time [ns since the Unix epoch, UTC], so a replay runs on the original time line; its
publish time is the wall-clock time it was written; its ``sequence`` is the pair index, which
ties the messages of one pair together. All messages are protobuf (schema encoding
``protobuf``, a full ``FileDescriptorSet`` per schema), readable by Foxglove, Rerun's MCAP
loader (``rerun session.mcap``) and ``mcap_protobuf``'s generic decoder.

Topics
------
=============================  ======================  ==============================================
``/<cam>/image/compressed``    foxglove.CompressedImage  the camera's image, bytes as received (JPEG)
``/<cam>/cloud_mask``          foxglove.CompressedImage  cloud mask, PNG 1-bit grey (decodes to 255 = cloud), lossless
``/pair/matches``              cbh.Matches               kept correspondences per method (x1, y1, x2, y2 px)
``/pair/points``               foxglove.PointCloud       frame ``enu``: x, y, z (= height) [m], miss [m],
                                                         x1, y1, x2, y2 [px] (float32), layer (int32)
``/pair/height_map``           foxglove.RawImage         32FC1 on camera 1's grid [m above the ENU origin],
                                                         NaN = unknown (lossless); decimated by
                                                         PairLayers.height_map_scale f > 1 when the map
                                                         is made of f × f blocks (the pipeline's is its
                                                         working-size map upsampled): 1/f² the bytes,
                                                         read back exactly
``/pair/histogram``            cbh.Histogram             edges_m (B + 1), counts (B)
``/pair/layers``               cbh.PairLayers            layers (height_m, altitude_m, cover, points,
                                                         confidence, motion_east_ms/motion_north_ms/
                                                         motion_spread_ms [m/s, absent = unknown],
                                                         motion_tracks, height_lo_m/height_hi_m
                                                         (the band) [m, absent = unknown] …),
                                                         cloud fraction,
                                                         flags (names) and flag_bits (cbh.flags.Flag),
                                                         diagnostics (name, value), timing;
                                                         written last: a pair is complete once it is there
``/service/status``            cbh.ServiceStatus         service counters, source states, full JSON
=============================  ======================  ==============================================

Metadata record ``cbh``: ``station_name``, ``station_toml`` (self-contained station),
``config_json`` (resolved pipeline config), ``cbh_version``, ``cameras``,
``recorder_start_utc`` (wall clock), ``session_start_utc`` (first capture time), ``file_index``.

Durability: each message is its own zstd chunk and the file is flushed after every pair; a
killed writer loses at most the pair in flight and :func:`recover` (``cbh inspect FILE
--repair OUT.mcap``) rewrites the rest into a valid file.
"""
from __future__ import annotations

from cbh.outputs.record.reader import RecordedImage, RecordedPair, Session, TopicInfo, open_session
from cbh.outputs.record.recover import RecoveryReport, recover
from cbh.outputs.record.source import RecordingSource
from cbh.outputs.record.writer import McapRecorder, cbh_version

__all__ = [
    "McapRecorder", "open_session", "recover", "Session", "RecordedPair", "RecordedImage",
    "TopicInfo", "RecoveryReport", "cbh_version", "RecordingSource",
]
