"""Top-down drawing of the arena and the MK-V with pygame (the only module that imports it).

Drawn from the same scene for ``rgb_array`` and ``human``: floor and slippery patches, obstacles,
the robot's trail, chassis outline, bumpers (lit red when pressed), the drive wheel, the steering
wheel at its current angle, the caster, and a strip of live readings.
"""

from __future__ import annotations

import math

import numpy as np

SIZE_PX = 600
"""Side of the rendered square image [pixels]."""

FLOOR = (236, 233, 224)
PATCH = (190, 215, 235)
OBSTACLE = (90, 90, 96)
TRAIL = (70, 120, 200)
CHASSIS = (240, 160, 40)
BUMPER = (40, 150, 60)
BUMPER_LIT = (220, 30, 30)
WHEEL = (30, 30, 30)
TEXT = (20, 20, 20)


class Renderer:
    def __init__(self, mode: str, fps: int):
        import pygame  # lazy: physics never needs it

        self.pg = pygame
        self.mode = mode
        self.fps = fps
        if mode == "human":
            pygame.display.init()
            self.screen = pygame.display.set_mode((SIZE_PX, SIZE_PX))
            pygame.display.set_caption("MK-V")
            self.clock = pygame.time.Clock()
        self.surface = pygame.Surface((SIZE_PX, SIZE_PX))
        pygame.font.init()
        self.font = pygame.font.Font(None, 18)

    def draw(self, env):
        pg = self.pg
        world = env.world
        lay = world.layout
        scale = (SIZE_PX - 34) / max(lay.width_m, lay.height_m)  # 24 px band for the text

        def px(x, y):
            return (17 + x * scale, SIZE_PX - 10 - y * scale)

        surf = self.surface
        surf.fill((255, 255, 255))
        pg.draw.polygon(surf, FLOOR, [px(0, 0), px(lay.width_m, 0), px(lay.width_m, lay.height_m),
                                      px(0, lay.height_m)])
        for x0, y0, x1, y1, _ in lay.patches:
            pg.draw.polygon(surf, PATCH, [px(x0, y0), px(x1, y0), px(x1, y1), px(x0, y1)])
        from mkv_env.world import WALL_RADIUS_M

        wpx = max(2, int(round(2 * WALL_RADIUS_M * scale)))
        for ax, ay, bx, by in lay.walls:
            pg.draw.line(surf, OBSTACLE, px(ax, ay), px(bx, by), wpx)
            for p in (px(ax, ay), px(bx, by)):
                pg.draw.circle(surf, OBSTACLE, p, wpx / 2)
        for cx, cy, w, h, ang in lay.boxes:
            c, s = math.cos(ang), math.sin(ang)
            pts = [(cx + c * x - s * y, cy + s * x + c * y)
                   for x, y in ((-w / 2, -h / 2), (w / 2, -h / 2), (w / 2, h / 2), (-w / 2, h / 2))]
            pg.draw.polygon(surf, OBSTACLE, [px(*p) for p in pts])
        for cx, cy, r in lay.cylinders:
            pg.draw.circle(surf, OBSTACLE, px(cx, cy), r * scale)
        if len(env.trail) > 1:
            pg.draw.lines(surf, TRAIL, False, [px(*p) for p in env.trail], 2)

        robot = world.robot
        rp = robot.params
        lw = robot.body.local_to_world

        def local_poly(points):
            return [px(*lw(p)) for p in points]

        pg.draw.polygon(surf, CHASSIS, local_poly(_rect(0, 0, rp.length_m, rp.width_m)))
        pg.draw.polygon(surf, TEXT, local_poly(_rect(0, 0, rp.length_m, rp.width_m)), 1)
        hl, hw, g = rp.length_m / 2, rp.width_m / 2, rp.bumper_gap_m
        fl, fr, rear = world.bumps
        bw = max(2, int(0.016 * scale))
        pg.draw.line(surf, BUMPER_LIT if fl else BUMPER, px(*lw((hl + g, 0))),
                     px(*lw((hl + g - 0.03, hw))), bw)
        pg.draw.line(surf, BUMPER_LIT if fr else BUMPER, px(*lw((hl + g, 0))),
                     px(*lw((hl + g - 0.03, -hw))), bw)
        pg.draw.line(surf, BUMPER_LIT if rear else BUMPER, px(*lw((-hl - g, -0.8 * hw))),
                     px(*lw((-hl - g, 0.8 * hw))), bw)
        rd = rp.drive_wheel_radius_m
        pg.draw.polygon(surf, WHEEL, local_poly(_rect(rp.drive_x_m, 0, 2 * rd, 0.025)))
        rs = rp.steer_wheel_radius_m
        pg.draw.polygon(surf, WHEEL,
                        local_poly(_rect(rp.steer_x_m, 0, 2 * rs, 0.02, robot.state.steer)))
        pg.draw.circle(surf, WHEEL, px(*lw(rp.caster_xy_m)), max(2, 0.012 * scale))
        pg.draw.line(surf, TEXT, px(*lw((0, 0))), px(*lw((hl * 0.8, 0))), 1)

        st = robot.state
        text = (f"drive {st.drive_current:+.2f} A  steer {st.steer_current:+.2f} A  "
                f"angle {math.degrees(st.steer):+.0f} deg  dist {env.tracker.distance_m:.1f} m  "
                f"jams {env.tracker.jams} escapes {env.tracker.escapes}")
        surf.blit(self.font.render(text, True, TEXT), (12, 2))

        if self.mode == "human":
            self.screen.blit(surf, (0, 0))
            pg.event.pump()
            pg.display.flip()
            self.clock.tick(self.fps)
            return None
        return np.transpose(np.array(pg.surfarray.pixels3d(surf)), (1, 0, 2)).copy()

    def close(self):
        if self.mode == "human":
            self.pg.display.quit()


def _rect(cx, cy, length, width, angle=0.0):
    c, s = math.cos(angle), math.sin(angle)
    return [(cx + c * x - s * y, cy + s * x + c * y)
            for x, y in ((-length / 2, -width / 2), (length / 2, -width / 2),
                         (length / 2, width / 2), (-length / 2, width / 2))]
