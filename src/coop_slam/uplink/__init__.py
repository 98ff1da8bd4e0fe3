"""A client's side of the radio: what its odometry's keyframes become on the way to the server
(:mod:`.records`), when they go (:mod:`.holdback`), what each message carries (:mod:`.planner`),
and the engine the client node and the bench drive (:mod:`.engine`)."""
