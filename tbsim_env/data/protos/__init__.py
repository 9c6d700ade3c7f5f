"""Protobuf schema of the WOMD ``Scenario`` (motion subset), written for tbsim.

``scenario.proto`` is the source; ``scenario_pb2.py`` is generated from it with
``python -m grpc_tools.protoc -I tbsim_env/data/protos --python_out=tbsim_env/data/protos
scenario.proto`` and committed (``tests/test_womd_reader.py`` checks that both agree).
The generated module needs protobuf >= 7.35.1 at runtime.
"""
