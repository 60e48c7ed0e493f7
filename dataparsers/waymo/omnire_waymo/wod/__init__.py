"""Waymo Open Dataset v1 message definitions (``waymo.open_dataset`` protobuf package).

``*.proto`` here are the dataset's own definitions (Copyright 2019 The Waymo Open Dataset
Authors, Apache License 2.0; see each file's header), with their import paths changed to
point into this package; ``*_pb2.py`` are generated from them by protoc 25
(``tools/generate_protos.py``, grpcio-tools 1.62.3) for the protobuf 4.25.x runtime.
"""
