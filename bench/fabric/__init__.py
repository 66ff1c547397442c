"""bench/fabric: one-hop latency and throughput between two processes (rap_sdk over
Zenoh vs raw zenoh-python into asyncio vs asyncio TCP), in-process stage-to-stage
delivery vs an asyncio.Queue hop, and the transport-thread to loop hand-off."""
