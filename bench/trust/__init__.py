"""bench/trust: the trust checker's evaluator against the same specs written by hand in
Python (µs per tick, same process, same trace), and its end-to-end verdict latency over
Zenoh against a raw RAP echo in the same run."""
