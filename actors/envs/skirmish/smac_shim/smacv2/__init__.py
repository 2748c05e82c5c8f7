"""A stand-in for oxwhirl's `smacv2` package that runs on skirmish (no StarCraft II); on the
import path only when you put its parent folder there (see the skirmish README)."""
