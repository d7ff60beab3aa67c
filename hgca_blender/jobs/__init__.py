"""The core's process and work in the background: `core.Job` runs `python -m hgca_core.cli` as a child process,
the jobs built on it (completion, drive, Install Core) put its answers into the scene, and `background` awaits
short core calls on a thread. What a job hands the core is read from the scene here (`job_inputs`,
`default_region`). Uses `scene`, never the operators or the interface."""
