"""bench/knowledge: replicated reads, writes, history and throughput of the knowledge
service and client, against a dict, Redis and a raw Zenoh query round trip."""
