-- wrk script: POSTs the JPEG files listed (one path per line) in the file
-- named by $IMAGES to /detect, cycling through them; $QUERY is appended.
local paths = {}
for line in io.lines(os.getenv("IMAGES")) do
  paths[#paths + 1] = line
end
local bodies = {}
for i, p in ipairs(paths) do
  local f = assert(io.open(p, "rb"))
  bodies[i] = f:read("*a")
  f:close()
end
local query = os.getenv("QUERY") or ""
local n = 0
request = function()
  n = n + 1
  local body = bodies[(n % #bodies) + 1]
  return wrk.format("POST", "/detect" .. query, {["Content-Type"] = "image/jpeg"}, body)
end
