"""The read-out add-on: a head that estimates the objects' state from the frozen tokens, fitted on the simulator's
true state (rendered aux frames, demonstration rows) before the policy trains, then fed to the trunk."""
