"""State and parameter estimators: the paper's pipeline and the baselines it is judged against."""
