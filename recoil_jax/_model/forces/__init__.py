"""The forces family (`docs/model.md`): what a part of the gun and a force are
(`family`: `Part`, `Force`), and one module per part, each defining its member and its
laws:

- `barrel`: the barrel, its recoil spring and its damper;
- `absorber`: the absorber and its contact: the coupling, the contact's force and width;
- `loads`: the breech force, its rounds and their events;
- `orifice`: the hydraulic buffer's throttling orifice;
- `recuperator`: the gas recuperator and its preload;
- `rails`: gravity along the rails and the friction's bound;
- `stop`: the battery stop;
- `counter_recoil`: the counter-recoil buffer;
- `mount`: the gun on the ground (a part, no force);
- `smoothing`: the smoothed switches every force is built from;
- `system`: the family's sum at one state (`Forces`, `forces`), the friction that takes
  what the others leave, and the structure that decides which a design has.
"""

__all__: list[str] = []
