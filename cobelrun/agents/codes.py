"""Integer codes the compiled tabular kernels take for policies, replay modes and sampling.

Kept apart from :mod:`cobelrun.agents.kernels` so that building and validating an agent does
not import numba (~0.35 s): the kernels are imported when an agent first runs trials.
"""

# Policies
EPSILON_GREEDY = 0
SOFTMAX = 1
POLICIES = {"epsilon_greedy": EPSILON_GREEDY, "softmax": SOFTMAX}

# Replay modes
REPLAY_OFF = 0
REPLAY_STEP = 1
REPLAY_TRIAL_END = 2
REPLAY_MODES = {"off": REPLAY_OFF, "step": REPLAY_STEP, "trial_end": REPLAY_TRIAL_END}

# Model memory sampling
SAMPLE_ALL = 0
SAMPLE_VISITED = 1
SAMPLING = {"all": SAMPLE_ALL, "visited": SAMPLE_VISITED}
