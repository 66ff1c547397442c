"""bench/fuzz: a bounded-in-time fuzz run against a running lidar-occlusion loop.

Every subscriber and queryable of the loop (the five MAPLE-K nodes in a maplek_runner
process, the knowledge service, one trust checker per shipped MAPLE-K spec) gets at
least ``--samples`` mutated samples, seeded and reproducible; the run reports crashes
(processes that died or stopped answering), rejections by reason, RSS before and after,
and whether the loop still closes afterwards. ``python -m bench.fuzz --help``.
"""
