"""Global adjustment: a continuous correction per run, observations as sparse rows, a banded robust solve."""
