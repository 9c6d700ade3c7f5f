"""Protobuf schemas read by tbsim, written for tbsim: the WOMD ``Scenario`` (motion subset) and
TensorFlow's ``tf.train.Example`` (the WOMD tf_example records, without TensorFlow).

``scenario.proto`` and ``tf_example.proto`` are the sources; ``scenario_pb2.py`` and
``tf_example_pb2.py`` are generated from them with ``python -m grpc_tools.protoc -I
tbsim_env/data/protos --python_out=tbsim_env/data/protos scenario.proto tf_example.proto``
(grpcio-tools 1.85, protoc 35.1) and committed (``tests/test_womd_reader.py`` and
``tests/test_tf_example_reader.py`` check that each agrees with its source).
The generated modules need protobuf >= 7.35.1 at runtime.
"""
