"""The shipped message definitions: faithful copies of the dataset's, and the committed
generated modules in step with them."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1]
TOOL = PKG / "tools" / "generate_protos.py"


def load_tool():
    spec = importlib.util.spec_from_file_location("generate_protos", TOOL)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_protos_are_the_datasets_with_package_imports(real_frame):
    tool = load_tool()
    upstream = real_frame.parent / "protos"
    for rel, name in tool.FILES.items():
        assert (tool.OUT / name).read_text() == tool._rewrite((upstream / rel).read_text()), name
        assert "Licensed under the Apache License, Version 2.0" in (tool.OUT / name).read_text()


def test_generated_modules_match_the_protos(tmp_path):
    pytest.importorskip("grpc_tools", reason="grpcio-tools==1.62.3 (extra 'protos') regenerates the modules")
    tool = load_tool()
    (tmp_path / "omnire_waymo" / "wod").mkdir(parents=True)
    tool.compile_protos(tmp_path)
    for name in tool.FILES.values():
        mod = name.replace(".proto", "_pb2.py")
        assert (tmp_path / "omnire_waymo" / "wod" / mod).read_text() == (tool.OUT / mod).read_text(), mod


def test_runtime_is_protobuf_4():
    import google.protobuf

    assert google.protobuf.__version__.startswith("4.")  # the generated code's runtime (and mediapipe's)
