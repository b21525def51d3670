"""Recording keys to MCAP (ros2 profile, the wire's CDR bytes verbatim) and replaying them."""
