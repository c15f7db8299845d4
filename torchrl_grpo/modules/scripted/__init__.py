"""Hand-written policies for highway-env's DiscreteMetaAction on Kinematics observations.

Every policy is a :class:`~tensordict.nn.TensorDictModule` reading ``"observation"``
(``[*batch, V, F]``) and writing an int64 ``"action"`` (``[*batch]``), so it plugs into
``env.rollout``, collectors and group rollouts like a learned actor. The policies keep
no state between calls: their decision depends on the current observation only, which
keeps them exact under snapshot branching.

- :mod:`~torchrl_grpo.modules.scripted.actions`: the meta actions, the
  :class:`~torchrl_grpo.modules.ScriptedPolicy` wrapper, constant and random policies;
- :mod:`~torchrl_grpo.modules.scripted.scene`: the :class:`~torchrl_grpo.modules.Scene` a driver
  reads from the observation, and the :class:`~torchrl_grpo.modules.Driver` base class;
- :mod:`~torchrl_grpo.modules.scripted.drivers`: the decisions of the driving policies;
- :mod:`~torchrl_grpo.modules.scripted.policies`: the driving policies;
- :mod:`~torchrl_grpo.modules.scripted.policy_registry`: the policies by name.

What a user needs is exported by :mod:`torchrl_grpo.modules`; the rest is imported from
its module.
"""
