"""`smacv2.env.starcraft2` on skirmish."""
