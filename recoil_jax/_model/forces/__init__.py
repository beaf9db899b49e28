"""The forces of the recoil system, one module per physical group (`docs/model.md`):

- `smoothing`: the smoothed switches every force is built from;
- `absorber`: the absorber's contact width and its characteristic penetration;
- `orifice`: the hydraulic buffer's throttling orifice;
- `recuperator`: the gas recuperator and its preload;
- `stop`: the battery stop;
- `counter_recoil`: the counter-recoil buffer;
- `rails`: gravity along the rails and the friction's bound;
- `loads`: the breech force, its rounds and their events;
- `system`: all forces of a design at one state (`Forces`, `forces`), the friction that
  takes what the others leave, and the structure that decides which a design has.
"""

__all__: list[str] = []
