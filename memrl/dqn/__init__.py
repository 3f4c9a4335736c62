"""Double DQN with prior knowledge: config schemas, learner, stages, loop (checkpoints live in
:mod:`memrl.checkpoint`)."""
