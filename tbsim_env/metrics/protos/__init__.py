"""Generated protobuf modules of the metrics package (``sim_agents_submission_pb2``)."""
