"""Recording: every session an MCAP log (ros2msg / CDR), a reader, metrics and replay."""
