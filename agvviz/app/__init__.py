"""The application: orchestration of run, diff, sweep, cluster, export, budget and audit over the library."""
