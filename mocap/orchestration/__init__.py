"""The orchestration layer: the chain of stages over one session folder (`pipeline`), the
demo, and the evaluation against a synthetic session's truth; `mocap.batch` runs it over
many sessions. Above the stages, below the command line."""
