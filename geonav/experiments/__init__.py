"""Transfer experiments: configs, the runner, convergence, reports and plots."""
