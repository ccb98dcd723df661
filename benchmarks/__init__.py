"""``btf bench`` suites: run time, memory and error of the stages, each against a reference
measured in the same run (these machines are noisy; ratios travel, seconds do not)."""
