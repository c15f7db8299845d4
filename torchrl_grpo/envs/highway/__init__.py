"""highway-env in TorchRL: HighwayEnv (highway-env itself, exact snapshots) and its codec.

:class:`~torchrl_grpo.envs.HighwayEnv` wraps every highway-env scenario with a state
that :class:`~torchrl_grpo.envs.highway.highway_codec.HighwayStateCodec` writes into tensors; the
codec's
field vocabulary and class registry are in :mod:`.schema`, its packed entity tables in
:mod:`.layout`. What a user needs is exported by :mod:`torchrl_grpo.envs`; the rest is
imported from its module.
"""
