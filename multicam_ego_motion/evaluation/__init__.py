"""Score an estimated trajectory against ground truth (`ego-motion evaluate`)."""
