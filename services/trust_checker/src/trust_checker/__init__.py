"""The trust checker: runtime verification of MAPLE-K loops in the LOLA/DSRV stream
language (both syntax eras of the RoboSAPIENS checker), on trace files, MQTT and the
Zenoh fabric. See docs/trust_checker.md."""
