"""Recordings on disk: the recording contract (MCAP, DESIGN §4), the formats agvviz reads, and
the files a run writes. The only package in agvviz that imports ``mcap``, ``rosbags`` and the
ROS decoders.

- :mod:`agvviz.recording.writer` — :class:`RecordingWriter` (atomic, Foxglove protobuf + agvviz JSON).
- :mod:`agvviz.recording.formats` — the registry of recording formats (MCAP/Foxglove, ROS 2,
  ROS 1), each one module with the same functions; :func:`~agvviz.recording.formats.decode`.
- :mod:`agvviz.recording.source` — a recording (``.mcap``, rosbag2 directory, ROS 1 bag), its
  scan (and sha256, in the same pass) and its messages with roles and stamps;
  :mod:`agvviz.recording.roles` — the role map.
- :mod:`agvviz.recording.reader` — :func:`iter_messages` of an MCAP file (streaming, salvages
  damaged files); below it :mod:`agvviz.recording.mcap_stream` (raw messages, header and
  metadata records) and :mod:`agvviz.recording.mcap_records` (the salvaging record loop).
- :mod:`agvviz.recording.raw` — what every format shares (raw messages, the read report,
  :class:`~agvviz.recording.raw.Recording`); :mod:`agvviz.recording.values` and
  :mod:`agvviz.recording.ros_messages` — decoded values built alike by every format.
- :mod:`agvviz.recording.contract` — :func:`inspect_recording`, :func:`format_report`.
- :mod:`agvviz.recording.schemas` — the ``agvviz.*`` JSON Schemas and their checker.
- :mod:`agvviz.recording.images` — uncompressed frames; :mod:`agvviz.recording.sidefiles`;
  :mod:`agvviz.recording.outputs` — the files a run writes.

The decoded messages themselves are :mod:`agvviz.model.messages`; topic names and roles
:mod:`agvviz.model.topics`.
"""
