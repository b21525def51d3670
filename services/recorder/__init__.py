"""Recording every key to MCAP (ros2 profile, CDR bytes verbatim) and replaying it."""
